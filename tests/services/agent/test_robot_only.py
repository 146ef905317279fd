"""What the agent says is on the robot only comes from what the depot holds, not from the agent's
current live rules: a run sent whole stays "0 chunks on the robot only" after the agent is restarted
with a narrower --live-include (it would keep most of that run on the robot if it saw it now)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.services.agent.harness import AgentProcess, Link, depot_chunks, log_whole_run, run_status
from tests.services.agent.test_summary_pull import recording_chunks
from tests.services.ingest.live_server import LiveServer
from tests.waiting import wait_for

pytestmark = [pytest.mark.sdk, pytest.mark.slow]


def robot_copy(depot: LiveServer, run_id: str) -> dict[str, Any] | None:
    answer = httpx.get(f"{depot.url}/v1/runs/{run_id}", headers=depot.headers, timeout=10).json()
    copy: dict[str, Any] | None = answer.get("robot_copy")
    return copy


def test_a_run_sent_whole_stays_held_after_a_narrower_restart(depot: LiveServer, link: Link, tmp_path: Path):
    spool = tmp_path / "spool"
    agent = AgentProcess(spool, link).start()  # everything live
    try:
        copy = tmp_path / "copy.rrd"
        log_whole_run(agent, copy, "run-whole", 30)
        total = len(recording_chunks(copy))
        wait_for(lambda: depot_chunks(depot, "run-whole") >= total, 60, "the depot to hold every chunk")
        wait_for(lambda: run_status(depot, "run-whole") == "closed", 60, "the run to close at the depot")
    finally:
        agent.stop()

    restarted = dt.datetime.now(dt.UTC)
    agent = AgentProcess(spool, link, live_include="/metrics/**").start()
    try:

        def reported_since_restart() -> dict[str, Any] | None:
            copy = robot_copy(depot, "run-whole")
            if copy is None or dt.datetime.fromisoformat(copy["reported_at"]) < restarted:
                return None
            return copy

        report = wait_for(reported_since_restart, 60, "the restarted agent's report of its copy")
        assert report["local_only_chunks"] == 0, report
        assert report["local_only_entities"] == []
        status = next(r for r in agent.status()["runs"] if r["run"] == "run-whole")
        assert status["local_only_chunks"] == 0, status
        assert depot_chunks(depot, "run-whole") >= total
    finally:
        agent.stop()
