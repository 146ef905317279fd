"""How an upload that does not finish ends: a client gone mid-body, a body refused for its robot id.
Neither leaves a live run, a hot file of a refused run, a catalog row of it, or a traceback."""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from services.rrd import ArrowMessage, iter_events
from tests.services.ingest.live_server import LiveServer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk

BAD_ROBOT_SCRIPT = """
import sys, rerun as rr
rec = rr.RecordingStream("fleet_bad_robot", recording_id="bad-robot-upload")
rec.save(sys.argv[1])
for i in range(3):
    rec.set_time("frame", sequence=i)
    rec.log("/speed", rr.Scalars([float(i)]))
rec.flush()
rec.send_property("fleet", rr.AnyValues(robot_id="../not-a-robot"))
rec.flush()
"""


def _run(server: LiveServer, run_id: str) -> httpx.Response:
    return httpx.get(f"{server.url}/v1/runs/{run_id}", timeout=10)


def test_a_client_gone_mid_upload_ends_its_run_without_a_traceback(
    server: LiveServer, recordings: dict[str, Recording]
):
    rec = recordings["scalars"]
    run_id = rec.recordings[0]["recording_id"]
    arrows = [e for e in iter_events(rec.path) if isinstance(e, ArrowMessage)]
    cut = arrows[len(arrows) // 2].offset  # several whole chunks, then the client is gone
    with socket.create_connection(("127.0.0.1", server.http_port), timeout=10) as sock:
        head = f"POST /v1/uploads HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: {len(rec.data)}\r\n\r\n"
        sock.sendall(head.encode() + rec.data[:cut])
        # The run exists once its first chunk is filed: then the client goes away mid-body.
        server.wait_for(lambda: _run(server, run_id).status_code == 200, timeout=30, what="the run filed")
    server.wait_for(
        lambda: _run(server, run_id).json()["status"] == "closed", timeout=30, what="the run closed after the cut"
    )
    assert 0 < _run(server, run_id).json()["chunks"] < len(arrows)  # what came whole is kept
    assert "Traceback" not in server.log.read_text()
    again = httpx.post(f"{server.url}/v1/uploads", content=rec.data, timeout=60)  # sending again completes it
    assert again.status_code == 200 and again.json()["chunks_duplicate"] > 0
    assert _run(server, run_id).json()["chunks"] == len(arrows)


def test_an_upload_refused_for_a_bad_robot_id_leaves_nothing(server: LiveServer, tmp_path: Path):
    path = tmp_path / "bad-robot.rrd"
    subprocess.run([sys.executable, "-c", BAD_ROBOT_SCRIPT, str(path)], check=True, timeout=120)
    response = httpx.post(f"{server.url}/v1/uploads", content=path.read_bytes(), timeout=60)
    assert response.status_code == 422 and "robot id" in response.json()["message"], response.text
    assert response.json()["accepted"]["runs"] == []
    assert _run(server, "bad-robot-upload").status_code == 404
    assert list((server.data_dir / "hot").glob("**/*.rrd")) == []
    assert httpx.get(f"{server.url}/v1/robots", timeout=10).json() in ([], {"robots": []})
