"""Promotion survives kill -9 at any moment: a real `fleet serve` promoting a ~58 MB run is killed
while sealing, while uploading the recording and as run.json appears, restarted each time, and
the run ends sealed with no chunk lost or doubled and no orphaned object, not even a temporary file."""

from __future__ import annotations

import hashlib
from pathlib import Path

import httpx
import pytest

from services.sealed.write import RUN_JSON
from tests.services.ingest.live_server import LiveServer
from tests.services.retention.conftest import log_run
from tests.services.retention.test_promote import ROBOT, chunk_ids
from tests.services.rrd.recordings import rerun_rrd_ok
from tests.waiting import wait_for

pytestmark = [pytest.mark.sdk, pytest.mark.slow]


def test_killed_mid_promotion_again_and_again_then_completed(tmp_path: Path, rerun_bin: str):
    run_id = "kill-run-1"
    original = log_run(tmp_path / "big.rrd", run_id, entities=10, frames=30, points=16000, robot=ROBOT)  # ~58 MB
    data = tmp_path / "data"
    hot, warm = data / "hot" / run_id, data / "warm"

    def files(root: Path) -> list[str]:
        found = (p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
        return sorted(f for f in found if not f.startswith("lakehouse/"))  # the Iceberg tables' files

    moments = [  # each one fresh on disk, reached by the promotion the (re)started server runs at once
        ("sealing", lambda: (hot / "seal").exists()),
        ("uploading the recording", lambda: any(Path(f).name.startswith(".tmp-") for f in files(warm))),
        ("uploading run.json", lambda: any(Path(f).name == RUN_JSON for f in files(warm))),
    ]
    server = LiveServer(data, promote_after_s="0", promote_interval_s="0.05").start()
    try:
        answer = httpx.post(f"{server.url}/v1/uploads", content=original.read_bytes(), timeout=120).json()
        assert answer["chunks_new"] == len(chunk_ids(original))
        for what, moment in moments:
            wait_for(moment, 60, what, interval=0.002)  # often: each moment is brief
            server.kill()
            server.start()

        def done() -> bool:
            return not hot.exists() and httpx.get(f"{server.url}/v1/runs/{run_id}", timeout=10).json()["tier"] == "warm"

        server.wait_for(done, timeout=120, what="the run sealed and its hot copy gone")
        run = httpx.get(f"{server.url}/v1/runs/{run_id}", timeout=10).json()
        out = tmp_path / "download.rrd"
        out.write_bytes(httpx.get(f"{server.url}/v1/runs/{run_id}/recording.rrd", timeout=120).content)
        query = {"query": f"SELECT count(*) AS n FROM text_logs WHERE run_id = '{run_id}'"}

        def logged() -> int:
            return int(httpx.post(f"{server.url}/v1/sql", json=query, timeout=60).json()["rows"][0][0])

        server.wait_for(lambda: logged() >= 30, timeout=60, what="the run's rows in the lakehouse's tables")
        assert logged() == 30  # one text log per frame, once: however often promotion was killed
    finally:
        server.stop()
    prefix = run["lifecycle"]["prefix"]
    assert [e["action"] for e in run["events"]] == ["promote"]
    ids = chunk_ids(out)
    assert len(ids) == len(set(ids)) and set(ids) == set(chunk_ids(original))  # no chunk lost, none twice
    rerun_rrd_ok(rerun_bin, "verify", str(out))
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", str(original), str(out))
    # No orphan, not even a half-written temporary file: the store holds what the catalog records.
    assert files(warm) == sorted([o["key"] for o in run["objects"]] + [f"{prefix}/{RUN_JSON}"])
    for obj in run["objects"]:
        assert hashlib.sha256((warm / obj["key"]).read_bytes()).hexdigest() == obj["sha256"]
