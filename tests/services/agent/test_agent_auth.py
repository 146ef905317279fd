"""The agent on a depot with auth on: the robot's ingest token opens its streams, its questions about
held chunks, its pulls and its reports, for its own robot only; a token for another robot is refused
and said so, with the data kept on the robot; the token never reaches a log or the spool."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.services.agent.harness import AgentProcess, Link, depot_chunks, log_whole_run
from tests.services.ingest.live_server import LiveServer
from tests.waiting import wait_for

pytestmark = [pytest.mark.sdk, pytest.mark.slow]


@pytest.fixture
def depot(tmp_path: Path) -> Iterator[LiveServer]:
    server = LiveServer(tmp_path / "depot", auth="on").start()
    yield server
    server.stop()


def ingest_token(depot: LiveServer, robot: str) -> str:
    answer = httpx.post(
        f"{depot.url}/v1/tokens", json={"scopes": ["ingest"], "robot": robot}, headers=depot.headers, timeout=10
    )
    assert answer.status_code == 201, answer.text
    return str(answer.json()["token"])


def spooled_and_logged(spool: Path, log: Path) -> bytes:
    return b"".join(p.read_bytes() for p in spool.rglob("*") if p.is_file()) + log.read_bytes()


def test_the_robots_token_carries_its_runs(depot: LiveServer, tmp_path: Path):
    token = ingest_token(depot, "robot-agent")
    link = Link(depot)
    agent = AgentProcess(tmp_path / "spool", link, token=token).start()
    try:
        log_whole_run(agent, tmp_path / "copy.rrd", "run-token", 10)
        wait_for(lambda: depot_chunks(depot, "run-token") > 0, 60, "the run at the depot")
        answer = httpx.get(f"{depot.url}/v1/runs/run-token", headers=depot.headers, timeout=10).json()
        assert answer["robot_id"] == "robot-agent"
        wait_for(lambda: agent.status()["link"].get("up"), 30, "the link up")
        assert agent.status()["link"].get("refused") is None
    finally:
        agent.stop()
        link.close()
    assert token.encode() not in spooled_and_logged(tmp_path / "spool", agent.log)


def test_another_robots_token_is_refused_and_the_run_kept(depot: LiveServer, tmp_path: Path):
    token = ingest_token(depot, "robot-other")
    link = Link(depot)
    agent = AgentProcess(tmp_path / "spool", link, token=token).start()
    try:
        log_whole_run(agent, tmp_path / "copy.rrd", "run-wrong", 10)
        refused = wait_for(
            lambda: agent.status()["link"].get("refused"),
            60,
            "the depot's refusal",
            detail=lambda: f"the agent said:\n{agent.log.read_text()[-6000:]}\nthe depot said:\n{depot.said()}",
        )
        assert "robot" in refused
        assert agent.spool_bytes("run-wrong") > 0  # kept on the robot
        status = httpx.get(f"{depot.url}/v1/runs/run-wrong", headers=depot.headers, timeout=10).status_code
        assert status == 404  # (a status, not the request: its token stays out of the report)
        assert "refused run run-wrong" in agent.log.read_text()
    finally:
        agent.stop()
        link.close()
    assert token.encode() not in spooled_and_logged(tmp_path / "spool", agent.log)
