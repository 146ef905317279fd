"""`fleet runs ls|show`, `fleet download`, `fleet view` against a real service."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from services.rrd import ArrowMessage, StoreKind, iter_events
from services.rrd.chunk import chunk_meta
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory, recordings: dict[str, Recording]) -> Iterator[LiveServer]:
    live = LiveServer(Path(tmp_path_factory.mktemp("cli-runs")) / "data").start()
    for name in ("points", "transforms"):
        assert httpx.post(f"{live.url}/v1/uploads", content=recordings[name].data, timeout=60).status_code == 200
    yield live
    live.stop()


def fleet(server: LiveServer, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([FLEET, *args, "--api-url", server.url], capture_output=True, text=True, timeout=120)


def test_runs_ls_and_show(server: LiveServer, recordings: dict[str, Recording]):
    points = recordings["points"].recordings[0]["recording_id"]
    table = fleet(server, "runs", "ls")
    assert table.returncode == 0 and points in table.stdout
    listed = json.loads(fleet(server, "runs", "ls", "--json", "--entity", "/world/**").stdout)
    assert points in {r["id"] for r in listed["runs"]}
    shown = fleet(server, "runs", "show", points)
    assert shown.returncode == 0 and "/world" in shown.stdout
    assert json.loads(fleet(server, "runs", "show", points, "--json").stdout)["id"] == points
    missing = fleet(server, "runs", "show", "no-such-run")
    assert missing.returncode == 1 and len(missing.stderr.strip().splitlines()) == 1
    assert "no run 'no-such-run'" in missing.stderr


def test_download_with_filters(server: LiveServer, recordings: dict[str, Recording], tmp_path: Path, rerun_bin: str):
    run_id = recordings["points"].recordings[0]["recording_id"]
    out = tmp_path / "part.rrd"
    result = fleet(server, "download", run_id, "-o", str(out), "--include", "/world/**")
    assert result.returncode == 0, result.stderr
    paths = {chunk_meta(e).entity_path for e in iter_events(out)
             if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING}
    assert paths and all(p == "/world" or p.startswith("/world/") for p in paths)
    assert subprocess.run([rerun_bin, "rrd", "verify", str(out)], capture_output=True).returncode == 0


def test_view_prints_the_rerun_command(server: LiveServer, recordings: dict[str, Recording]):
    run_id = recordings["points"].recordings[0]["recording_id"]
    result = fleet(server, "view", run_id, "--include", "/world/**")
    assert result.returncode == 0
    command = result.stdout.strip()
    assert command.startswith("rerun ") and f"/v1/runs/{run_id}/recording.rrd?include=%2Fworld%2F%2A%2A" in command
