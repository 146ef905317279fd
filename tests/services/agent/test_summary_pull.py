"""Summary live, full on demand: the live rules send only the metrics and logs; an engineer pulls a
window of the camera, and the depot's run gains exactly that window's chunks (and the newest ones
before it, so the scene at its start is complete), each once."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.decoder import iter_events
from services.rrd.messages import ArrowMessage, StoreKind
from services.runs.download import EntityFilter
from services.runs.latest_at import ChunkEntry, select_chunks
from tests.services.agent.harness import AgentProcess, Link, depot_chunks, download, log_whole_run, run_status
from tests.services.ingest.live_server import LiveServer
from tests.waiting import wait_for

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

LIVE = ["/metrics/**", "/logs/**"]


def recording_chunks(path: Path) -> dict[bytes, tuple[str, ChunkMeta]]:
    """chunk id -> (entity, metadata) of the recording's data chunks."""
    out: dict[bytes, tuple[str, ChunkMeta]] = {}
    for event in iter_events(path):
        if isinstance(event, ArrowMessage) and event.store_id.kind == StoreKind.RECORDING:
            meta = chunk_meta(event)
            out[meta.chunk_id] = (meta.entity_path, meta)
    return out


def test_summary_live_then_a_pulled_window(depot: LiveServer, link: Link, tmp_path: Path):
    agent = AgentProcess(tmp_path / "spool", link, live_include=",".join(LIVE)).start()
    try:
        copy = tmp_path / "copy.rrd"
        log_whole_run(agent, copy, "run-summary", 40)
        chunks = recording_chunks(copy)
        live = EntityFilter(LIVE)
        summary = {cid for cid, (entity, _) in chunks.items() if live(entity)}
        wait_for(lambda: run_status(depot, "run-summary") == "closed", 60, "the summary run to close at the depot")
        served = recording_chunks(download(depot, "run-summary", tmp_path / "summary.rrd"))
        assert set(served) == summary  # the camera, the lidar and the map stayed on the robot
        copy_answer = wait_for(
            lambda: (a := httpx.get(f"{depot.url}/v1/runs/run-summary", timeout=10).json()).get("robot_copy") and a,
            60,
            "the agent's report of its copy",
        )
        assert copy_answer["robot_copy"]["local_only_chunks"] == len(chunks) - len(summary)
        assert "/world/robot/camera" in copy_answer["robot_copy"]["local_only_entities"]

        pull = httpx.post(
            f"{depot.url}/v1/runs/run-summary/pull",
            json={"include": ["/world/robot/camera"], "timeline": "frame", "start": "10", "end": "19"},
            timeout=10,
        )
        assert pull.status_code == 202, pull.text
        pull_id = pull.json()["pull"]["id"]

        def done() -> bool:
            pulls = httpx.get(f"{depot.url}/v1/runs/run-summary/pulls", timeout=10).json()
            state = str(next(p["state"] for p in pulls["pulls"] if p["id"] == pull_id))
            assert state != "failed", pulls
            return state == "done"

        wait_for(done, 90, "the pull to be done")
        camera = EntityFilter(["/world/robot/camera"])
        entries = [ChunkEntry.of_meta(meta, True, "frame") for cid, (entity, meta) in chunks.items() if camera(entity)]
        window, _ = select_chunks(entries, (10, 19), True, lambda unknown: unknown)
        assert window, "the window holds camera chunks"
        wait_for(lambda: run_status(depot, "run-summary") == "closed", 60, "the pull's stream to end")
        after = recording_chunks(download(depot, "run-summary", tmp_path / "pulled.rrd"))
        assert set(after) == summary | window
        assert depot.metric("fleet_ingest_chunks_duplicate_total") == 0
        # the catalog's count of the run's chunks is written by its next flush
        wait_for(lambda: depot_chunks(depot, "run-summary") == len(summary | window), 30, "the catalog's chunk count")
        # the pulled window is at the depot now: no longer reported as on the robot only
        left = len(chunks) - len(summary | window)
        wait_for(
            lambda: (
                httpx.get(f"{depot.url}/v1/runs/run-summary", timeout=10).json()["robot_copy"]["local_only_chunks"]
                == left
            ),
            60,
            f"the agent to report {left} chunks on the robot only after the pull",
        )
        assert next(r for r in agent.status()["runs"] if r["run"] == "run-summary")["local_only_chunks"] == left
    finally:
        agent.stop()
