"""Depot nodes as real `fleet serve` processes on one Postgres catalog and one warm folder, and a
recording made with the real SDK, for the ownership suites of this package."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import httpx

from services.cluster.relay import request_of
from services.rrd.decoder import iter_events
from services.rrd.messages import ArrowMessage
from tests.services.ingest.live_server import LiveServer

KEY = "k" * 48  # the signing key every node shares
ROBOT_SCRIPT = """
import sys, rerun as rr
rec = rr.RecordingStream("cluster", recording_id=sys.argv[1])
rec.set_sinks(rr.FileSink(sys.argv[2]))
rec.send_property("fleet", rr.AnyValues(robot_id="r1"))
for i in range(int(sys.argv[3])):
    rec.set_time("step", sequence=i)
    rec.log("/metrics/speed", rr.Scalars(float(i)))
rec.flush()
"""


def node(tmp_path: Path, name: str, catalog_url: str, **settings: str) -> LiveServer:
    return LiveServer(
        tmp_path / name,
        auth="on",
        auth_key=KEY,
        node_id=name,
        catalog_url=catalog_url,
        warm_url=(tmp_path / "warm").as_uri(),
        cold_url=(tmp_path / "cold").as_uri(),
        lease_s="2",
        promote_interval_s="0.5",
        retention_interval_s="3600",
        **settings,
    )


def recording(tmp_path: Path, run_id: str, steps: int) -> Path:
    """A run of `steps` one-row chunks of robot r1, written by the SDK to a file."""
    path = tmp_path / f"{run_id}.rrd"
    env = {**os.environ, "RERUN_FLUSH_NUM_ROWS": "1"}
    subprocess.run([sys.executable, "-c", ROBOT_SCRIPT, run_id, str(path), str(steps)], check=True, env=env)
    return path


def requests_of(path: Path) -> list[bytes]:
    """The file's messages as WriteMessagesRequests, as the SDK streams them."""
    return [r for r in (request_of(e) for e in iter_events(path)) if r is not None]


def chunk_count(path: Path) -> int:
    return sum(isinstance(e, ArrowMessage) for e in iter_events(path))


def token(admin_of: LiveServer, scopes: list[str], robot: str | None = None) -> str:
    made = httpx.post(
        f"{admin_of.url}/v1/tokens",
        json={"scopes": scopes, "robot": robot, "name": robot or "-".join(scopes)},
        headers=admin_of.headers,
        timeout=10,
    )
    assert made.status_code == 201, made.text
    return str(made.json()["token"])


def bearer(value: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {value}"}
