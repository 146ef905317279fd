"""The lakehouse's upkeep: small files compacted with every row kept, snapshots expired, files no
snapshot reaches removed (a deleted run's data with them), and compaction giving way to a writer
that changed a file first."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pyarrow.compute as pc
import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from services.lakehouse import maintenance
from services.lakehouse import sync as lake_sync
from services.lakehouse.tables import Lakehouse
from services.sealed.tiers import Tiers
from services.storage.objectstore import open_store
from tests.services.lakehouse.test_sync import now, scalars, seal


@pytest.fixture
def tiers(tmp_path: Path) -> Tiers:
    return Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri()))


def seal_each(catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse, runs: int) -> None:
    """`runs` runs of one robot and day, each copied by a sync of its own (a file each)."""
    for i in range(runs):
        seal(catalog, tiers, f"run-{i}", [float(i), float(i) + 0.5])
        lake_sync.sync(lake, catalog, tiers.warm, now)


def data_files(lake: Lakehouse) -> list[str]:
    return [task.file.file_path for task in lake.table("scalars").scan().plan_files()]


def test_small_files_are_compacted_with_every_row_kept(
    catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse
) -> None:
    seal_each(catalog, tiers, lake, 6)
    before = scalars(lake)
    assert len(data_files(lake)) == 6
    replaced, written = maintenance.compact(lake.table("scalars"))
    assert (replaced, written) == (6, 1)
    after = scalars(lake)
    assert len(data_files(lake)) == 1
    assert after.num_rows == before.num_rows == 12
    assert pc.sum(after["value"]).as_py() == pc.sum(before["value"]).as_py()
    assert sorted(after["log_time_ns"].to_pylist()) == sorted(before["log_time_ns"].to_pylist())
    assert set(after["frame"].to_pylist()) == {0, 1}  # a timeline column compacted too


def test_a_deleted_runs_file_leaves_the_bucket_once_its_snapshots_expire(
    catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse
) -> None:
    seal_each(catalog, tiers, lake, 2)
    (gone,) = [f for f in data_files(lake) if "run-0" in scalars_of(lake, f)]
    with session_scope(catalog, write=True) as session:
        queries.mark_deleted(session, "run-0", now())
    lake_sync.sync(lake, catalog, tiers.warm, now)
    assert Path(gone.removeprefix("file://")).exists()  # old snapshots still reach it
    report = maintenance.maintain(lake, tiers.warm, now() + dt.timedelta(seconds=5), dt.timedelta(seconds=0))
    assert report.expired_snapshots >= 2 and report.removed_files >= 1  # scalars: two appends; the delete is current
    assert not Path(gone.removeprefix("file://")).exists()
    assert scalars(lake)["run_id"].to_pylist() == ["run-1", "run-1"]  # the rest reads as before
    table = lake.table("scalars")
    current = table.current_snapshot()
    assert current is not None and [s.snapshot_id for s in table.metadata.snapshots] == [current.snapshot_id]


def test_nothing_younger_than_the_kept_snapshots_is_removed(
    catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse
) -> None:
    seal_each(catalog, tiers, lake, 2)
    stray = tiers.warm.url.removeprefix("file://") + "/lakehouse/fleet/scalars/data/in-flight.parquet"
    Path(stray).write_bytes(b"a commit under way elsewhere")
    report = maintenance.maintain(lake, tiers.warm, now(), dt.timedelta(hours=1))
    assert report.removed_files == 0 and Path(stray).exists()
    assert scalars(lake).num_rows == 4


def test_compaction_gives_way_to_a_run_replaced_meanwhile(
    catalog: sessionmaker[Session], tiers: Tiers, lake: Lakehouse
) -> None:
    seal_each(catalog, tiers, lake, 4)
    table = lake.table("scalars")  # compaction planned on this snapshot
    group = [task.file for task in table.scan().plan_files()]
    seal(catalog, tiers, "run-2", [9.0])  # run-2 extracted again and copied: its old file goes
    lake_sync.sync(lake, catalog, tiers.warm, now)
    assert maintenance._rewrite(table, group) is False
    rows = scalars(lake)
    assert rows.num_rows == 7 and sorted(rows.filter(pc.equal(rows["run_id"], "run-2"))["value"].to_pylist()) == [9.0]
    assert not [p for p in Path(table.location().removeprefix("file://")).rglob("compacted-*")]


def scalars_of(lake: Lakehouse, path: str) -> list[str]:
    import pyarrow.parquet as pq

    return [str(v) for v in pq.read_table(path.removeprefix("file://"))["run_id"].to_pylist()]
