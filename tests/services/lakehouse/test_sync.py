"""The lakehouse's sync: a run's analytics rows copied into the Iceberg tables exactly once, replaced
when its files change, removed when it is deleted, over a folder and an S3 (moto) warm store and
both catalogs (the Iceberg catalog on Postgres itself, or a SQLite file beside DuckDB's)."""

from __future__ import annotations

import datetime as dt
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc
import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.queries import ObjectRecord
from core.states import Tier
from services.lakehouse import sync as lake_sync
from services.lakehouse.schemas import TABLES
from services.lakehouse.tables import Lakehouse, open_lakehouse
from services.sealed.tiers import Tiers
from services.storage.objectstore import open_store
from tests.seaweedfs import seaweedfs
from tests.services.analytics.conftest import START_2026_03_01_NS, catalog_run, write_scalars

DATE = "2026-03-01"


BUCKET, REGION = "fleet-warm", "us-east-1"


@pytest.fixture(scope="module")
def seaweed_endpoint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    import boto3

    with seaweedfs(tmp_path_factory.mktemp("seaweedfs")) as endpoint:
        boto3.client(
            "s3", endpoint_url=endpoint, region_name=REGION, aws_access_key_id="test", aws_secret_access_key="test"
        ).create_bucket(Bucket=BUCKET)  # one bucket, a prefix per test
        yield endpoint


@pytest.fixture(params=["file", pytest.param("s3-seaweedfs", marks=[pytest.mark.s3server, pytest.mark.slow])])
def tiers(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Tiers:
    """A warm store in a folder, or on a real S3 server (pyiceberg's S3 reads do not go through
    boto3, so moto's in-process mock cannot stand in for it)."""
    if request.param == "file":
        return Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri()))
    for name, value in (
        ("AWS_ACCESS_KEY_ID", "test"),
        ("AWS_SECRET_ACCESS_KEY", "test"),
        ("AWS_DEFAULT_REGION", REGION),
    ):
        monkeypatch.setenv(name, value)
    endpoint = request.getfixturevalue("seaweed_endpoint")
    warm = open_store(f"s3://{BUCKET}/{tmp_path.name}", endpoint_url=endpoint, region=REGION)
    return Tiers(warm, warm)


def now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def seal(
    catalog: sessionmaker[Session], tiers: Tiers, run_id: str, values: list[float], robot: str = "robot-1"
) -> None:
    """A sealed run with a scalars file, recorded the way promotion records its analytics objects."""
    key = write_scalars(tiers.warm, robot, DATE, run_id, values)
    catalog_run(catalog, run_id, robot, DATE, {})
    with session_scope(catalog, write=True) as session:
        size = tiers.warm.head(key).size
        queries.replace_analytics(
            session, run_id, [ObjectRecord("analytics/scalars", key, Tier.WARM, size, str(values))]
        )


def scalars(lake: Lakehouse) -> pa.Table:
    return lake.table("scalars").scan().to_arrow()


def sync(lake: Lakehouse, catalog: sessionmaker[Session], tiers: Tiers) -> lake_sync.SyncReport:
    return lake_sync.sync(lake, catalog, tiers.warm, now)


def test_a_sealed_run_is_copied_once_with_its_robot_date_and_exact_times(
    catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse
) -> None:
    seal(catalog, tiers, "run-a", [1.0, 2.0, 3.0])
    seal(catalog, tiers, "run-b", [5.0, 6.0])
    report = sync(lake, catalog, tiers)
    assert (report.runs, report.rows, report.left) == (2, 5, 0)
    rows = scalars(lake).sort_by([("run_id", "ascending"), ("value", "ascending")])
    assert rows["run_id"].to_pylist() == ["run-a"] * 3 + ["run-b"] * 2
    assert set(rows["robot_id"].to_pylist()) == {"robot-1"}
    assert set(rows["date"].to_pylist()) == {dt.date(2026, 3, 1)}
    assert rows["log_time_ns"].to_pylist()[:3] == [START_2026_03_01_NS + i for i in range(3)]
    assert rows["frame"].to_pylist() == [0, 1, 2, 0, 1]
    assert sync(lake, catalog, tiers).runs == 0  # nothing pending: nothing copied again
    assert scalars(lake).num_rows == 5


def snapshots(lake: Lakehouse, name: str) -> int:
    return len(lake.table(name).metadata.snapshots)


def test_a_table_the_batch_brings_nothing_to_gets_no_commit(
    catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse
) -> None:
    from catalog import corpus

    seal(catalog, tiers, "run-a", [1.0, 2.0])  # scalars only: no text logs, transforms, tags, events, metrics
    sync(lake, catalog, tiers)
    made = {name: snapshots(lake, name) for name in TABLES}
    assert made == {name: int(name in ("scalars", "runs")) for name in TABLES}
    with session_scope(catalog, write=True) as session:
        corpus.add_tags(session, "run-a", ["night-shift"], "alice", now())
    sync(lake, catalog, tiers)
    grown = {name for name in TABLES if snapshots(lake, name) > made[name]}
    assert grown == {"runs", "run_tags"}  # the run's row replaced, its tag added: nothing else committed
    with session_scope(catalog, write=True) as session:
        corpus.remove_tags(session, "run-a", ["night-shift"])
    sync(lake, catalog, tiers)
    assert lake.table("run_tags").scan().to_arrow().num_rows == 0  # the delete alone is committed


def test_new_files_replace_a_runs_rows_and_a_delete_removes_them(
    catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse
) -> None:
    seal(catalog, tiers, "run-a", [1.0, 2.0, 3.0])
    seal(catalog, tiers, "run-b", [5.0])
    sync(lake, catalog, tiers)
    seal(catalog, tiers, "run-a", [7.0, 8.0])  # extracted again: new rows
    sync(lake, catalog, tiers)
    rows = scalars(lake)
    assert sorted(rows.filter(pc.equal(rows["run_id"], "run-a"))["value"].to_pylist()) == [7.0, 8.0]
    with session_scope(catalog, write=True) as session:
        queries.mark_deleted(session, "run-a", now())
    report = sync(lake, catalog, tiers)
    assert report.removed == 1
    assert scalars(lake)["run_id"].to_pylist() == ["run-b"]


@pytest.mark.parametrize("tiers", ["file"], indirect=True)
def test_two_syncs_at_once_leave_one_copy(
    catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse, fresh_catalog_url: str
) -> None:
    for i in range(4):
        seal(catalog, tiers, f"run-{i}", [float(i)] * 10)
    other = open_lakehouse(fresh_catalog_url, tiers.warm)
    errors: list[BaseException] = []

    def run(target: Lakehouse) -> None:
        try:
            lake_sync.sync(target, catalog, tiers.warm, now)
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(target,)) for target in (lake, other)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    other.close()
    assert not errors
    counts = pc.value_counts(scalars(lake)["run_id"]).to_pylist()
    assert sorted((c["values"], c["counts"]) for c in counts) == [(f"run-{i}", 10) for i in range(4)]


def mirrored(
    lake: Lakehouse, catalog: sessionmaker[Session], name: str
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Table `name`'s rows in the lakehouse and in the catalog, in one order."""
    from catalog.sql_tables import catalog_tables

    with session_scope(catalog) as session:
        held = catalog_tables(session, [name])[name].to_pylist()
    copied = lake.table(name).scan().to_arrow().to_pylist()
    key = lambda row: sorted((k, str(v)) for k, v in row.items())  # noqa: E731
    return sorted(copied, key=key), sorted(held, key=key)


def test_catalog_rows_follow_tags_events_metrics_and_deletion(
    catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse
) -> None:
    from catalog import corpus
    from catalog.corpus import EvaluationFacts, EventFacts, MetricFacts

    seal(catalog, tiers, "run-a", [1.0])
    seal(catalog, tiers, "run-b", [2.0])
    with session_scope(catalog, write=True) as session:
        corpus.add_tags(session, "run-a", ["night-shift", "dock-2"], "alice", now())
        bump = EventFacts("bump", "warn", "log_time", "timestamp", 5, 9, "person", "alice", "a bump")
        corpus.add_event(session, "run-a", "robot-1", bump, now(), "ev-0000000000000001")
        metric = MetricFacts("distance_m", 12.5, None)
        evaluation = EvaluationFacts("run-b", "robot-1", 1, "final", [], [metric], False, None)
        corpus.replace_evaluations(session, [evaluation], now())
    sync(lake, catalog, tiers)
    for name in ("runs", "run_tags", "events", "run_metrics"):
        copied, held = mirrored(lake, catalog, name)
        assert copied == held and held, name
    with session_scope(catalog, write=True) as session:
        corpus.remove_tags(session, "run-a", ["dock-2"])
        queries.mark_deleted(session, "run-b", now())
    report = sync(lake, catalog, tiers)
    assert report.removed == 1
    for name in ("runs", "run_tags", "events", "run_metrics"):
        copied, held = mirrored(lake, catalog, name)
        assert copied == held, name
    assert [r["tag"] for r in mirrored(lake, catalog, "run_tags")[0]] == ["night-shift"]
    assert {r["id"]: r["tier"] for r in mirrored(lake, catalog, "runs")[0]} == {"run-a": "warm", "run-b": "deleted"}
    assert "run-b" not in scalars(lake)["run_id"].to_pylist()
