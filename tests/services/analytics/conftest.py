"""Fixtures for the analytics tests: nodes (ingest + retention) over local or S3 stores with the
SQL API on top, recordings logged with the real SDK, and analytics files written directly."""

from __future__ import annotations

import datetime as dt
import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyarrow as pa
import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import session_scope
from catalog.models import RunObject
from catalog.queries import save_run
from services.analytics.extract import SCALARS, Extractor
from services.analytics.service import Analytics
from services.analytics.sql import Limits
from services.analytics.store import write_analytics
from services.api.app import create_app
from services.retention.service import PROMOTE, plan, run_plan
from services.storage.objectstore import ObjectStore
from tests.catalog.records import run_record
from tests.services.retention.conftest import Node, make_node, tiers  # noqa: F401 - fixtures used here

DAY_NS = 86_400 * 10**9
START_2026_03_01_NS = 1_772_323_200 * 10**9  # 2026-03-01T00:00:00Z
HOUR_NS = 3_600 * 10**9

# Every SDK script starts with this: one RecordingStream per run, all in one process (one SDK import).
SDK_PRELUDE = """
import json, math, time
import numpy as np
import rerun as rr


def recording(path, run_id, robot, start_ns):
    rec = rr.RecordingStream("fleet-analytics", recording_id=run_id)
    rec.save(str(path))
    rec.send_property("fleet", rr.AnyValues(robot_id=robot))
    rec.send_recording_start_time_nanos(start_ns)
    return rec


def finish(rec):
    rec.flush()
    rec.disconnect()
"""


def log_with_sdk(script: str, *, flush_rows: int | None = None) -> Any:
    """Run `script` (after SDK_PRELUDE) with the real SDK in a subprocess, so each test module gets its
    own SDK state; returns the JSON the script prints on its last line (its ground truth), if any."""
    env = {**os.environ, **({"RERUN_FLUSH_NUM_ROWS": str(flush_rows)} if flush_rows else {})}
    done = subprocess.run(
        [sys.executable, "-c", SDK_PRELUDE + script], env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr[-3000:]
    lines = done.stdout.strip().splitlines()
    return json.loads(lines[-1]) if lines else None


OPENED: list[Analytics] = []


def opened(analytics: Analytics) -> Analytics:
    """`analytics`, its SQL workers stopped when the test ends (idle ones hold ~100 MB each)."""
    OPENED.append(analytics)
    return analytics


@pytest.fixture(autouse=True)
def _stop_sql_workers() -> Iterator[None]:
    yield
    while OPENED:
        OPENED.pop().close()


def analytics_for(node: Node, limits: Limits | None = None) -> Analytics:
    return opened(Analytics(node.context, limits or Limits()))


def api(node: Node, limits: Limits | None = None, *, raise_server_exceptions: bool = True) -> TestClient:
    """The service's REST API over `node` (ingest, retention and analytics), in process."""
    app = create_app(node.context, node.ingest, node.retention, analytics_for(node, limits))
    return TestClient(app, raise_server_exceptions=raise_server_exceptions)


def upload_all(node: Node, paths: list[Path]) -> None:
    for path in paths:
        report = node.upload(path)
        assert report.chunks_new > 0, path


def promote_all(node: Node) -> list[str]:
    """Promote every closed hot run now (the clock moved past promote_after); returns the run ids."""
    node.clock.advance(hours=1)
    outcomes = run_plan(node.retention, plan(node.retention, [PROMOTE]))
    assert outcomes and all(o.ok for o in outcomes), [o.to_dict() for o in outcomes]
    return [o.action.run_id for o in outcomes]


def sql_rows(client: TestClient, query: str) -> list[dict[str, Any]]:
    """The JSON answer of POST /v1/sql as a list of {column: value} (checking it succeeded)."""
    response = client.post("/v1/sql", json={"query": query})
    assert response.status_code == 200, response.text
    body = response.json()
    names = [c["name"] for c in body["columns"]]
    assert body["row_count"] == len(body["rows"])
    return [dict(zip(names, row, strict=True)) for row in body["rows"]]


def write_scalars(
    store: ObjectStore, robot: str, date: str, run_id: str, values: list[float], entity: str = "/battery"
) -> str:
    """Write one run's `scalars` file the way promotion does (write_analytics); returns its key."""
    n = len(values)
    spill = Path(tempfile.mkdtemp(prefix="scalars-"))
    extractor = Extractor(run_id, spill)
    extractor.append(
        "scalars",
        pa.table(
            {
                "run_id": pa.array([run_id] * n),
                "entity": pa.array([entity] * n),
                "component": pa.array([SCALARS] * n),
                "instance": pa.array([0] * n, pa.int32()),
                "value": pa.array(values, pa.float64()),
                "frame": pa.array(range(n), pa.int64()),
                "log_time": pa.array([START_2026_03_01_NS + i for i in range(n)], pa.timestamp("ns")),
            }
        ),
    )
    (written,) = write_analytics(store, extractor.files(), run_id, robot, date)
    shutil.rmtree(spill)
    return written.key


def catalog_run(
    catalog: sessionmaker[Session], run_id: str, robot: str, date: str, keys: dict[str, str], tier: str = "warm"
) -> None:
    """The catalog's side of a run whose analytics files are `keys` (name -> key, e.g.
    {"analytics/scalars": key}): what promotion records, so SQL reads those files."""
    day = dt.date.fromisoformat(date)
    at = dt.datetime.combine(day, dt.time(), dt.UTC)
    with session_scope(catalog) as session:
        save_run(
            session,
            run_record(run_id, at, robot_id=robot, application_id="test", tier=tier, bytes=1),
            at,
        )
        for name, key in keys.items():
            session.merge(RunObject(run_id=run_id, name=name, key=key, tier="warm", size=1, sha256="0" * 64))
