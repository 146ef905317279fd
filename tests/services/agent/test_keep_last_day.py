"""The robot keeps its last day, and never what the depot has not confirmed: a spool over its cap
while the link is down keeps everything (and says so); once the depot holds the run sealed, the
robot deletes its copy."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.services.agent.harness import AgentProcess, Link, download, log_whole_run, same_recording
from tests.services.ingest.live_server import LiveServer
from tests.waiting import wait_for

pytestmark = [pytest.mark.sdk, pytest.mark.slow]


@pytest.fixture
def depot(tmp_path: Path) -> Iterator[LiveServer]:
    server = LiveServer(tmp_path / "depot", promote_after_s="0", promote_interval_s="1").start()
    yield server
    server.stop()


def test_unconfirmed_runs_are_kept_over_the_cap_and_confirmed_ones_go(
    depot: LiveServer, tmp_path: Path, rerun_bin: str
):
    link = Link(depot)
    agent = AgentProcess(tmp_path / "spool", link, max_bytes="100000", retain_hours="0").start()
    try:
        link.cut()
        copy = tmp_path / "copy.rrd"
        log_whole_run(agent, copy, "run-kept", 25)
        size = agent.spool_bytes("run-kept")
        assert size > 1_000_000

        def over_cap() -> bool:
            retention = agent.status().get("retention") or {}
            return int(retention.get("over_by", 0)) > 0

        wait_for(over_cap, 60, "the agent to find its spool over the cap with nothing confirmed")
        assert agent.spool_bytes("run-kept") == size  # kept whole
        assert "needs" in agent.log.read_text() and "bytes freed" in agent.log.read_text()

        link.restore()
        wait_for(lambda: agent.spool_bytes("run-kept") == 0, 120, "the confirmed run to leave the robot")
        served = download(depot, "run-kept", tmp_path / "served.rrd")
        same, why = same_recording(rerun_bin, copy, served)
        assert same, why
        assert depot.metric("fleet_ingest_bytes_duplicate_total") <= 0.05 * size  # the gap went once
    finally:
        agent.stop()
        link.close()
