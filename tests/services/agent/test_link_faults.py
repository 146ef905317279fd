"""The agent and the depot as real processes, a robot on the real SDK streaming to the agent, and
the link between agent and depot through proxies the test cuts and restores: whatever happens to the
link, the depot or the agent, the depot's run ends equal to the robot's own FileSink copy, with no
one uploading anything, and what is sent again is what the broken link swallowed, plus at most 5% of
the gap."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from services.rrd import ArrowMessage, iter_events
from tests.services.agent.harness import (
    AgentProcess,
    Link,
    Robot,
    depot_chunks,
    depot_equals_copy,
)
from tests.services.ingest.live_server import LiveServer
from tests.tcp_proxy import HANG, REFUSE
from tests.waiting import wait_for

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

FRAMES = 25  # per step: about 1.5 MB
H2_DEFAULT_WINDOW = 65_535


@pytest.fixture
def agent(tmp_path: Path, link: Link) -> Iterator[AgentProcess]:
    process = AgentProcess(tmp_path / "spool", link, stall_s="5").start()
    yield process
    process.stop()


def resent_bytes(depot: LiveServer, agent: AgentProcess) -> int:
    """Chunk bytes that crossed the link twice: the agent's re-sends of what the depot lacked after a
    break, and what the depot received but already held."""
    resent = agent.metric("fleet_agent_resent_bytes")
    return int(resent + depot.metric("fleet_ingest_bytes_duplicate_total"))


def caught_up(depot: LiveServer, agent: AgentProcess, run_id: str) -> bool:
    """The depot holds every chunk the agent's spool has of the run: nothing is in flight. (On a
    loaded machine the agent may lag the robot; what it had in flight at a break is re-sent, and
    is not what the break's gap measures.)"""
    try:
        path = agent.spool / "runs" / run_id / "run.rrd"
        spooled = sum(1 for e in iter_events(path) if isinstance(e, ArrowMessage) and e.chunk_id)
    except Exception:  # the spool's last message half written: ask again
        return False
    return spooled > 0 and depot_chunks(depot, run_id) >= spooled


def largest_message(agent: AgentProcess, run_id: str) -> int:
    """The largest message of the run the agent spooled, in bytes."""
    path = agent.spool / "runs" / run_id / "run.rrd"
    return max(e.size for e in iter_events(path) if isinstance(e, ArrowMessage))


@pytest.mark.parametrize("how", [REFUSE, HANG])
def test_a_cut_link_loses_nothing_and_resends_little(
    depot: LiveServer, link: Link, agent: AgentProcess, tmp_path: Path, rerun_bin: str, how: str
):
    copy = tmp_path / "copy.rrd"
    robot = Robot("steps", agent.url, str(copy), "run-cut", "3", str(FRAMES))
    robot.expect("STEP 1")
    wait_for(lambda: caught_up(depot, agent, "run-cut"), 60, "the depot to hold the run's first chunks")
    sent_at_cut = agent.metric("fleet_agent_sent_bytes")
    link.cut(how)
    if how == REFUSE:
        # The open stream is cut at once, but what the agent wrote into it before it heard (a loaded
        # machine may take a while) is in flight, not gap: the gap is what is logged once it knows.
        wait_for(lambda: agent.status()["link"].get("up") is False, 60, "the agent to find the link refused")
    at_cut = agent.spool_bytes("run-cut")
    robot.go_on()
    robot.expect("STEP 2")  # logged while the link is down: the SDK never noticed
    wait_for(lambda: agent.spool_bytes("run-cut") - at_cut > 1_000_000, 30, "the gap to reach the spool")
    gap = agent.spool_bytes("run-cut") - at_cut
    if how == HANG:  # a silent link: only the agent's keepalive pings find it dead
        wait_for(lambda: agent.status()["link"].get("up") is False, 60, "the agent to find the silent link dead")
    # What the agent handed the link after the cut went nowhere: a refused stream's last writes, or
    # what a silent link's socket buffers took before the agent found it dead (from nothing to a few
    # hundred KB, as the kernel sized them). That is re-sent by necessity; the gap itself is not.
    swallowed = agent.metric("fleet_agent_sent_bytes") - sent_at_cut
    link.restore()
    robot.go_on()
    robot.expect("STEP 3")
    robot.go_on()
    robot.expect("DONE")
    robot.finish()
    depot_equals_copy(depot, "run-cut", copy, rerun_bin, tmp_path)
    resent = resent_bytes(depot, agent)
    # Beyond what was counted then, what cannot be counted on a loaded machine: a write under way
    # (not yet counted as sent) when the test read the count, as large as a message, and what a
    # connection the agent opens into a silent link after that takes before its stream's first
    # window (HTTP/2's default 64 KiB: the depot never answered it) is spent. Twice in CI the re-sent
    # bytes went 104 and 107 KB over the bound without these; the gap is over 1.3 MB.
    in_flight = largest_message(agent, "run-cut") + (H2_DEFAULT_WINDOW if how == HANG else 0)
    print(f"link {how}: gap {gap} bytes, swallowed {swallowed:.0f} bytes, re-sent {resent} bytes")
    assert resent <= swallowed + in_flight + 0.05 * gap, (resent, swallowed, in_flight, gap)


def test_a_depot_killed_mid_run_loses_nothing(depot: LiveServer, agent: AgentProcess, tmp_path: Path, rerun_bin: str):
    copy = tmp_path / "copy.rrd"
    robot = Robot("steps", agent.url, str(copy), "run-depot-kill", "3", str(FRAMES))
    robot.expect("STEP 1")
    wait_for(lambda: caught_up(depot, agent, "run-depot-kill"), 60, "the depot to hold the run's first chunks")
    sent_at_kill = agent.metric("fleet_agent_sent_bytes")
    depot.kill()
    at_kill = agent.spool_bytes("run-depot-kill")
    robot.go_on()
    robot.expect("STEP 2")
    gap = agent.spool_bytes("run-depot-kill") - at_kill
    swallowed = agent.metric("fleet_agent_sent_bytes") - sent_at_kill  # written before the agent heard
    depot.start()
    robot.go_on()
    robot.expect("STEP 3")
    robot.go_on()
    robot.expect("DONE")
    robot.finish()
    depot_equals_copy(depot, "run-depot-kill", copy, rerun_bin, tmp_path)
    assert gap > 0
    resent = resent_bytes(depot, agent)
    assert resent <= swallowed + 0.05 * gap, (resent, swallowed, gap)


def test_an_agent_killed_mid_run_loses_nothing(depot: LiveServer, link: Link, tmp_path: Path, rerun_bin: str):
    """The SDK's stream breaks with the agent and never reconnects: the rest of the run reaches the
    agent again by the FileSink copy it watches, and the depot gets each chunk once."""
    watched = tmp_path / "robot-files"
    watched.mkdir()
    agent = AgentProcess(tmp_path / "spool", link, watch=str(watched), file_idle_s="2").start()
    copy = watched / "run-agent-kill.rrd"
    try:
        robot = Robot("steps", agent.url, str(copy), "run-agent-kill", "3", str(FRAMES))
        robot.expect("STEP 1")
        wait_for(lambda: depot_chunks(depot, "run-agent-kill") > 0, 60, "the depot to hold the run's first chunks")
        agent.kill()
        robot.go_on()
        robot.expect("STEP 2")
        agent.start()
        robot.go_on()
        robot.expect("STEP 3")
        robot.go_on()
        robot.expect("DONE")
        robot.finish()
        depot_equals_copy(depot, "run-agent-kill", copy, rerun_bin, tmp_path)
        assert int(depot.metric("fleet_ingest_bytes_duplicate_total")) <= 0.05 * copy.stat().st_size
    finally:
        agent.stop()


def test_a_robot_that_only_writes_files_reaches_the_depot(
    depot: LiveServer, link: Link, tmp_path: Path, rerun_bin: str
):
    watched = tmp_path / "robot-files"
    watched.mkdir()
    agent = AgentProcess(tmp_path / "spool", link, watch=str(watched), file_idle_s="2").start()
    try:
        copy = watched / "run-file.rrd"
        robot = Robot("file", str(copy), "run-file", str(FRAMES))
        robot.expect("DONE")
        robot.finish()
        depot_equals_copy(depot, "run-file", copy, rerun_bin, tmp_path)
    finally:
        agent.stop()
