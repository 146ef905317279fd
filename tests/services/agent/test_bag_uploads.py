"""The agent and the real depot (`fleet serve`, auth on): the MCAP files in a watched folder (a
closed rosbag2 bag of two splits, a lone file) reach the depot under the robot's token, each bag's
splits in one run, each file once; a restart sends nothing again, and a file touched after its
upload is sent again and filed once (the depot says it already held it)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from services.agent.state import AgentState
from tests.services.agent.harness import AgentProcess, Link
from tests.services.agent.mcap_files import write_bag, write_mcap
from tests.services.agent.test_agent_auth import ingest_token
from tests.services.ingest.live_server import LiveServer
from tests.waiting import wait_for

pytestmark = [pytest.mark.slow]

BAG = "rosbag2_2024_01_31-12_00_00"
ROBOT = "robot-bags"


@pytest.fixture
def depot(tmp_path: Path) -> Iterator[LiveServer]:
    server = LiveServer(tmp_path / "depot", auth="on").start()
    yield server
    server.stop()


def uploaded(agent: AgentProcess, count: int) -> bool:
    bags = agent.status()["bags"]
    if bags["failed"]:  # a refusal is final: say it now rather than wait out the timeout
        raise AssertionError(f"the depot refused: {bags['failures']}")
    return bool(agent.status()["running"]) and bags["uploaded"] == count and bags["pending"] == 0


def uploads_logged(agent: AgentProcess) -> int:
    return agent.log.read_text().count("INFO:     fleet.agent: uploading ")


def test_the_agent_uploads_a_rosbag2_bag_and_a_lone_mcap_file_once(depot: LiveServer, tmp_path: Path):
    token = ingest_token(depot, ROBOT)
    watched = tmp_path / "recordings"
    write_bag(watched / BAG, splits=2)
    lone = write_mcap(watched / "arm calibration.mcap", messages=5)  # other bytes than the bag's splits
    spool = tmp_path / "spool"
    link = Link(depot)
    settings = {"token": token, "watch": str(watched), "bag_idle_s": "2"}
    agent = AgentProcess(spool, link, **settings).start()
    try:
        wait_for(lambda: uploaded(agent, 3), 120, "the three MCAP files uploaded", detail=lambda: str(agent.status()))
        for run_id, application in ((BAG, "rosbag2"), ("arm_calibration", "mcap")):
            answer = httpx.get(f"{depot.url}/v1/runs/{run_id}", headers=depot.headers, timeout=10)
            assert answer.status_code == 200, answer.text
            assert (answer.json()["robot_id"], answer.json()["application_id"]) == (ROBOT, application)
        assert agent.metric("fleet_agent_bags") == 3  # pending + uploaded + failed
        assert agent.metric("fleet_agent_bag_uploaded_bytes") == sum(p.stat().st_size for p in watched.rglob("*.mcap"))
        agent.stop()
        state = AgentState(spool, readonly=True)
        try:
            records = state.bags()
        finally:
            state.close()
        assert {r.run_id for r in records.values()} == {BAG, "arm_calibration"}
        assert all(r.state == "uploaded" and r.import_id for r in records.values()), records
        sent = uploads_logged(agent)
        assert sent == 3

        agent = AgentProcess(spool, link, **settings).start()  # a restart: nothing is sent again...
        st = lone.stat()
        os.utime(lone, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))  # ...but a file touched since
        held = agent.log.read_text().count("already held")
        wait_for(lambda: agent.log.read_text().count("already held") > held, 60, "the touched file sent again")
        # files go oldest first, the touched one last: had the others been sent again, it would show
        assert uploads_logged(agent) == sent + 1
        wait_for(lambda: uploaded(agent, 3), 30, "the restarted agent's count", detail=lambda: str(agent.status()))
    finally:
        agent.stop()
        link.close()
    assert token.encode() not in agent.log.read_bytes()
