"""The real SDK streams into a real `fleet serve`, which is killed part-way; the FileSink copy is
uploaded afterwards; the run held equals the copy, every chunk once, the token never stored."""

from __future__ import annotations

import subprocess
from pathlib import Path

import httpx
import pytest

from services.rrd import ArrowMessage, iter_events
from services.rrd.chunk import read_chunk
from services.rrd.errors import RrdError
from tests.services.ingest.live_server import LiveServer, start_robot
from tests.services.rrd.recordings import rerun_rrd_ok

pytestmark = pytest.mark.sdk


def _chunk_ids(path: Path) -> list[bytes]:
    return [e.chunk_id for e in iter_events(path) if isinstance(e, ArrowMessage)]  # type: ignore[misc]


def _chunk_ids_so_far(path: Path) -> list[bytes]:
    """The chunk ids of a hot file being written: none while it is created and still empty."""
    try:
        return _chunk_ids(path)
    except (FileNotFoundError, RrdError):  # not there yet, empty, or a message half-written
        return []


def test_kill_during_stream_then_upload_the_copy(server: LiveServer, tmp_path: Path, rerun_bin: str):
    copy, run_id = tmp_path / "copy.rrd", "e2e-run-1"
    robot = start_robot("scene", server.grpc_url, str(copy), run_id)
    assert robot.stdout is not None and robot.stdin is not None
    assert robot.stdout.readline().strip() == "HALF"
    hot = server.data_dir / "hot" / run_id / "run.rrd"
    server.wait_for(lambda: len(_chunk_ids_so_far(hot)) > 10, what="the first half on disk")
    server.kill()  # kill -9 in the middle of the robot's stream
    server.start()  # recovery: torn tails trimmed, runs back in the catalog
    robot.stdin.write("go\n")
    robot.stdin.flush()
    _, err = robot.communicate(timeout=120)
    assert robot.returncode == 0, err

    received = set(_chunk_ids(hot))
    answer = httpx.post(f"{server.url}/v1/uploads", content=copy.read_bytes(), timeout=120).json()
    everything = _chunk_ids(copy)
    assert answer["runs"] == [run_id]
    assert answer["chunks_new"] + answer["chunks_duplicate"] == len(everything)
    assert answer["chunks_duplicate"] == len(received) > 0
    held = _chunk_ids(hot)
    assert len(held) == len(set(held)) == len(everything)  # every chunk, once

    # Equal to the robot's copy, with the property entity that carried the token set apart.
    filtered = {}
    for name, path in (("copy", copy), ("held", hot)):
        out = tmp_path / f"{name}-filtered.rrd"
        subprocess.run(
            [rerun_bin, "rrd", "filter", "--drop-entity", "/__properties/fleet", str(path), "-o", str(out)],
            check=True,
            capture_output=True,
        )
        filtered[name] = out
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", filtered["copy"], filtered["held"])
    properties = [
        read_chunk(e).to_pylist()
        for e in iter_events(hot)
        if isinstance(e, ArrowMessage) and read_chunk(e).schema.metadata[b"rerun:entity_path"] == b"/__properties/fleet"
    ]
    assert len(properties) == 1
    (row,) = properties[0]
    assert row["robot_id"] == ["robot-e2e"] and row["site"] == ["lab-3"]
    assert "token" not in row  # every field kept but the token
    assert b"do-not-store" not in hot.read_bytes()


def test_two_hundred_streams_at_once(server: LiveServer):
    n = 200
    robot = start_robot("many", server.grpc_url, str(n))
    assert robot.stdout is not None and robot.stdin is not None
    try:
        assert robot.stdout.readline().strip() == "READY"
        server.wait_for(lambda: server.metric("fleet_live_streams") == n, what=f"{n} open streams")
        # a run is hot from its first data chunk, which may follow its stream's opening a little
        server.wait_for(lambda: server.metric("fleet_live_runs") == n, what=f"{n} live runs")
    finally:
        robot.stdin.write("done\n")
        robot.stdin.flush()
        robot.communicate(timeout=120)
    server.wait_for(lambda: server.metric("fleet_live_streams") == 0, what="streams to end")
    assert server.metric("fleet_live_runs") == 0  # every run closed when its stream ended
    assert server.metric("fleet_ingest_chunks_new_total") >= 2 * n  # RecordingInfo + one scalar each
