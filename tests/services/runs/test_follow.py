"""`recording.rrd?follow=true`: a live view over plain HTTP, ending with a footer when the run closes."""

from __future__ import annotations

import threading
from pathlib import Path

import httpx
import pytest

from tests.services.ingest.live_server import LiveServer, start_robot
from tests.services.rrd.recordings import rerun_rrd_ok

pytestmark = pytest.mark.sdk


def test_follow_streams_a_live_run_until_it_closes(server: LiveServer, tmp_path: Path, rerun_bin: str):
    copy, run_id = tmp_path / "copy.rrd", "follow-run-1"
    robot = start_robot("live", server.grpc_url, str(copy), run_id)
    assert robot.stdout is not None and robot.stdin is not None
    assert robot.stdout.readline().strip() == "READY"  # sent by the SDK: not yet filed by the depot, maybe
    server.wait_for(
        lambda: httpx.get(f"{server.url}/v1/runs/{run_id}/recording.rrd", timeout=10).status_code == 200,
        what="the live run to be served",
    )
    received = bytearray()
    first_data = threading.Event()
    done = threading.Event()

    def read() -> None:
        url = f"{server.url}/v1/runs/{run_id}/recording.rrd"
        with httpx.stream("GET", url, params={"follow": "true"}, timeout=120) as response:
            for piece in response.iter_raw():
                received.extend(piece)
                first_data.set()
        done.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    assert first_data.wait(60), "nothing arrived while the run was live"
    assert not done.is_set()  # still open: the run is live
    robot.stdin.write("go\n")
    robot.stdin.flush()
    _, err = robot.communicate(timeout=120)
    assert robot.returncode == 0, err
    assert done.wait(60), "the response did not end when the run closed"
    out = tmp_path / "followed.rrd"
    out.write_bytes(bytes(received))
    rerun_rrd_ok(rerun_bin, "verify", out)  # ends with End and a footer
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", copy, out)  # every chunk, the later ones too

    windowed = httpx.get(
        f"{server.url}/v1/runs/{run_id}/recording.rrd", params={"follow": "true", "timeline": "frame"}, timeout=30
    )
    assert windowed.status_code == 422 and "'follow'" in windowed.json()["message"]
