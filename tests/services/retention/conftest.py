"""Fixtures for retention tests: a node (ingest + retention) over local or S3 (moto) stores, a
settable clock, and runs logged with the real SDK."""

from __future__ import annotations

import datetime as dt
import io
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

import services.node
from catalog.db import create_engine
from services.facts.identity import SecretFields
from services.ingest.service import IngestReport, IngestService
from services.lakehouse.tables import Lakehouse, open_lakehouse
from services.policies import Policies, Policy, PolicyOverride
from services.retention.service import Retention
from services.rrd import iter_events
from services.sealed.tiers import Tiers
from services.storage.objectstore import ObjectStore, open_store
from tests.services.ingest import feeding
from tests.services.nodes import ingest_of, node_of

WARM_BUCKET, COLD_BUCKET = "fleet-warm", "fleet-cold"


class Clock:
    """A clock tests move by hand (retention ages are days)."""

    def __init__(self) -> None:
        self.now = dt.datetime.now(dt.UTC)

    def __call__(self) -> dt.datetime:
        return self.now

    def advance(self, **delta: float) -> dt.datetime:
        self.now += dt.timedelta(**delta)
        return self.now


@dataclass
class Node:
    """One service node's ingest and retention sides on one data dir and catalog."""

    root: Path
    tiers: Tiers
    catalog: sessionmaker[Session]
    clock: Clock
    ingest: IngestService
    retention: Retention
    restarts: list[IngestService] = field(default_factory=list)

    @property
    def context(self) -> services.node.Node:
        """What its sides share, as `fleet serve` passes it to them (settings of `root`/data)."""
        return self.retention.node

    def upload(self, path: Path | bytes) -> IngestReport:
        return feeding.upload(self.ingest, iter_events(io.BytesIO(path) if isinstance(path, bytes) else path))


NodeFactory = Callable[..., Node]


def _s3_env(monkeypatch: pytest.MonkeyPatch) -> None:
    for name, value in (
        ("AWS_ACCESS_KEY_ID", "test"),
        ("AWS_SECRET_ACCESS_KEY", "test"),
        ("AWS_DEFAULT_REGION", "us-east-1"),
    ):
        monkeypatch.setenv(name, value)


@pytest.fixture(params=["file", "s3-moto"])
def tiers(request: pytest.FixtureRequest, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Tiers]:
    """Warm and cold stores: two local folders, or two S3 buckets (moto) with cold as a copy target."""
    if request.param == "file":
        yield Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri()))
        return
    _s3_env(monkeypatch)
    from moto import mock_aws

    with mock_aws():
        import boto3

        client = boto3.client("s3", region_name="us-east-1")
        client.create_bucket(Bucket=WARM_BUCKET)
        client.create_bucket(Bucket=COLD_BUCKET)
        # moto's mock answers inside botocore: reads that bypass it (on the event loop) would go to
        # the network, so these stores read through botocore alone
        yield Tiers(
            open_store(f"s3://{WARM_BUCKET}/depot", region="us-east-1", loop_reads=False),
            open_store(f"s3://{COLD_BUCKET}/depot", region="us-east-1", loop_reads=False),
        )


@pytest.fixture
def make_node(tmp_path: Path, fresh_catalog_url: str) -> Iterator[NodeFactory]:
    """Build a node over given stores with a catalog of its own (DuckDB or Postgres); a second call
    on the same root is a restart."""
    engine = create_engine(fresh_catalog_url)
    catalog = sessionmaker(engine)
    made: list[IngestService] = []
    lakes: list[Lakehouse] = []

    def make(
        tiers: Tiers,
        *,
        clock: Clock | None = None,
        promote_after_s: float = 600.0,
        warm_days: float = 30.0,
        cold_days: float = 365.0,
        overrides: tuple[PolicyOverride, ...] = (),
        restore_days: float = 7.0,
        promote_below_free_bytes: int = 0,
        free_bytes: Callable[[], int] | None = None,
        recover: bool = True,
        secret_fields: SecretFields | None = None,
        lakehouse: bool | None = None,
    ) -> Node:
        clock = clock or Clock()
        # As `fleet serve` runs by default, with the lakehouse: over a folder (pyiceberg reads S3
        # without boto3, so moto's in-process S3 cannot serve it; tests of it on S3 use SeaweedFS).
        lake = None
        if lakehouse if lakehouse is not None else tiers.warm.url.startswith("file:"):
            lake = open_lakehouse(fresh_catalog_url, tiers.warm)
            lakes.append(lake)
        context = node_of(
            tmp_path,
            catalog,
            tiers=tiers,
            clock=clock,
            default_robot="robot-0",
            secret_fields=secret_fields,
            lakehouse=lake,
        )
        ingest = ingest_of(context)
        made.append(ingest)
        if recover:
            ingest.recover()
        retention = Retention(
            context,
            Policies(Policy("default", warm_days, cold_days), overrides),
            ingest,
            promote_after=dt.timedelta(seconds=promote_after_s),
            promote_below_free_bytes=promote_below_free_bytes,
            restore_days=restore_days,
            free_bytes=free_bytes,
        )
        return Node(tmp_path, tiers, catalog, clock, ingest, retention)

    yield make
    for ingest in made:
        ingest.hot.close()
    for lake in lakes:
        lake.close()
    engine.dispose()


def log_run(
    path: Path,
    recording_id: str,
    *,
    entities: int = 10,
    frames: int = 30,
    points: int = 2000,
    robot: str | None = None,
    application: str = "fleet-test",
    text: bool = True,
    chunk_rows: int | None = None,
) -> Path:
    """A run logged with the real SDK: `entities` point clouds (one chunk each, or one per
    `chunk_rows` frames), a static
    entity, optional text logs, and the robot's identity property. Runs in a subprocess so each
    recording gets its own SDK state."""
    import os
    import subprocess
    import sys

    script = f"""
import numpy as np, rerun as rr
rr.init({application!r}, recording_id={recording_id!r}, spawn=False)
rr.save({str(path)!r})
{f"rr.send_property('fleet', rr.AnyValues(robot_id={robot!r}))" if robot else ""}
rr.log('/world/static', rr.TextDocument('map'), static=True)
rng = np.random.default_rng(7)
for i in range({frames}):
    rr.set_time('frame', sequence=i)
    rr.set_time('sim', duration=i * 0.1)
    for e in range({entities}):
        rr.log(f'/world/e{{e}}', rr.Points3D(rng.random(({points}, 3), dtype=np.float32)))
    {"rr.log('/logs', rr.TextLog(f'step {i}', level='INFO'))" if text else "pass"}
"""
    env = {**os.environ, **({"RERUN_FLUSH_NUM_ROWS": str(chunk_rows)} if chunk_rows else {})}
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120, env=env)
    return path


def listing(store: ObjectStore) -> list[str]:
    """The store's keys but the lakehouse's (its tables' files outlive a deleted run's rows until their
    snapshots expire: tests/services/lakehouse checks the rows)."""
    return [info.key for info in store.list() if not info.key.startswith("lakehouse/")]
