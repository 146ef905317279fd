"""`fleet runs pull|pulls`, and what `fleet runs show` says of a robot's copy, against a real service."""

from __future__ import annotations

import re
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.retention.conftest import log_run

pytestmark = pytest.mark.sdk

RUN, ROBOT = "cli-pulled-run", "robot-7"


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    folder = Path(tmp_path_factory.mktemp("cli-pulls"))
    recording = log_run(folder / "run.rrd", RUN, entities=2, frames=3, points=20, robot=ROBOT)
    live = LiveServer(folder / "data").start()
    assert httpx.post(f"{live.url}/v1/uploads", content=recording.read_bytes(), timeout=60).status_code == 200
    yield live
    live.stop()


def fleet(server: LiveServer, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([FLEET, *args, "--api-url", server.url], capture_output=True, text=True, timeout=120)


def test_pull_then_list_then_show(server: LiveServer):
    asked = fleet(
        server, "runs", "pull", RUN, "--include", "/world/**", "--timeline", "frame", "--start", "1", "--end", "2"
    )
    assert asked.returncode == 0, asked.stderr
    found = re.fullmatch(
        rf"(pull-[0-9a-f]{{12}}): pending, for robot {ROBOT}'s agent \(--include /world/\*\* frame 1..2\)\n",
        asked.stdout,
    )
    assert found, asked.stdout
    pull_id = found.group(1)
    again = fleet(
        server, "runs", "pull", RUN, "--include", "/world/**", "--timeline", "frame", "--start", "1", "--end", "2"
    )
    assert again.stdout.startswith(f"{pull_id}: pending")  # the same pull, not a twin

    listed = fleet(server, "runs", "pulls", RUN)
    assert listed.returncode == 0 and pull_id in listed.stdout and "pending" in listed.stdout

    copy = {
        "chunks": 10,
        "bytes": 1000,
        "local_only_chunks": 4,
        "local_only_bytes": 400,
        "keeps_until": "2026-11-25T08:00:00Z",
    }
    assert httpx.put(f"{server.url}/v1/runs/{RUN}/robot-copy", json=copy, timeout=30).status_code == 200
    shown = fleet(server, "runs", "show", RUN)
    assert shown.returncode == 0, shown.stderr
    assert f"robot copy on {ROBOT}" in shown.stdout and "only on the robot: 4 chunks, 400 bytes" in shown.stdout
    assert "keeps it until 2026-11-25 08:00:00 UTC" in shown.stdout and pull_id in shown.stdout


def test_errors_are_one_line(server: LiveServer):
    no_timeline = fleet(server, "runs", "pull", RUN, "--start", "1")
    assert no_timeline.returncode == 1 and len(no_timeline.stderr.strip().splitlines()) == 1
    assert "parameter 'timeline'" in no_timeline.stderr
    unknown = fleet(server, "runs", "pulls", "no-such-run")
    assert unknown.returncode == 1 and "no run 'no-such-run'" in unknown.stderr
    bad = fleet(server, "runs", "pull", RUN, "--include", "world")
    assert bad.returncode == 1 and "'world' is not an entity path pattern" in bad.stderr
