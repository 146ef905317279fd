"""Three nodes on one catalog and bucket, one of them killed mid-run and never restarted.

Robots stream live with the real SDK to node A (GrpcSink + FileSink); their copies, as they stand
mid-run, are uploaded to node B. Robots with `fleet agent` stream through it to a load balancer that
sends each new connection to A, else C. Node A is then killed (SIGKILL): the SDK robots' streams
die with it and their complete copies are uploaded to B once they end, as a robot's upload job does,
again if B answers 503 (while the dead owner's lease has yet to run out); the agents reconnect through
the balancer to C and send from their spools what A never confirmed. In the end every run is in the
catalog once, sealed in the warm tier once (by one node), equal to its robot's copy with every chunk
once; the catalog-wide retention job never ran on two nodes at once; B knows A is dead; neither B nor C
logged an error."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import pytest

from tests.services.agent.harness import AgentProcess, Robot
from tests.services.cluster.harness import (
    BalancedLink,
    Cluster,
    Node,
    Problems,
    SdkRobot,
    check_logs,
    chunks_in,
    expect_owner,
    upload,
    verify_sealed,
    wait_settled,
)
from tests.waiting import holds_within

pytestmark = [pytest.mark.sdk, pytest.mark.slow, pytest.mark.postgres, pytest.mark.s3server]

SDK_ROBOTS, AGENT_ROBOTS = 2, 2
STEPS, FRAMES = 3, 12  # frames of about 60 kB (5 chunks) per step; the kill comes after step 2
# How often an agent asks which chunks the depot holds. 30 s: A dies before any agent is told A holds
# something. 1 s: agents are told A holds chunks that die with A; once the run's new owner answers
# their checks, they must ask again and re-send those before the run is sealed without them.
AGENT_CHECKS_S = ["30", "1"]
UPLOAD_WAIT_S = 60  # a robot's upload job retrying 503s: the dead owner's lease (2 s) and then some
SETTLE_S = 180  # every run sealed: reconnections, the lease, FLEET_PROMOTE_AFTER_S, on a busy machine


@pytest.mark.parametrize("agent_check_s", AGENT_CHECKS_S)
def test_a_node_killed_mid_run_loses_nothing_and_nothing_is_sealed_twice(
    cluster: Cluster, tmp_path: Path, rerun_bin: str, agent_check_s: str
):
    a, b, c = (cluster.add(name) for name in ("node-a", "node-b", "node-c"))
    cluster.start("node-a", "node-b", "node-c")
    sdk_runs = [f"sdk-run-{k}" for k in range(1, SDK_ROBOTS + 1)]
    agent_runs = [f"agent-run-{k}" for k in range(1, AGENT_ROBOTS + 1)]
    runs = sdk_runs + agent_runs
    copies = {run_id: tmp_path / f"{run_id}.rrd" for run_id in runs}
    tokens = {run_id: cluster.ingest_token(f"robot-{run_id}") for run_id in sdk_runs}
    agent_token = cluster.ingest_token("robot-agent")  # tests/services/agent/robot.py's robot
    problems = Problems()

    link = BalancedLink([a, c])
    agents: list[AgentProcess] = []
    sdk_robots: list[SdkRobot] = []
    agent_robots: list[Robot] = []
    try:
        for run_id in sdk_runs:
            sdk_robots.append(
                SdkRobot(a.grpc_url, copies[run_id], run_id, f"robot-{run_id}", tokens[run_id], STEPS, FRAMES)
            )
        for k, run_id in enumerate(agent_runs):
            agent = link.agent(tmp_path / f"spool-{k}", agent_token, check_s=agent_check_s).start()
            agents.append(agent)
            agent_robots.append(Robot("steps", agent.url, str(copies[run_id]), run_id, str(STEPS), str(FRAMES)))
        robots: list[SdkRobot | Robot] = [*sdk_robots, *agent_robots]

        # 1. every run live on A; the SDK robots' copies, as they stand, uploaded to B
        for robot in robots:
            robot.expect("STEP 1")
        # Asked of node-b, which answers from the catalog alone (node-a answers its hot runs from
        # ingest's view before its catalog flush): every run reached node-a and is filed.
        held = holds_within(lambda: all((b.run(r) or {}).get("chunks", 0) > 0 for r in runs), 60)
        assert held, f"not every run reached node-a and the catalog\n{cluster.diagnosis(runs)}"
        for robot in sdk_robots:
            in_copy = len(chunks_in(robot.copy))
            answer = upload(b, robot.copy, robot.token)
            problems.check(
                answer["runs"] == [robot.run_id] and answer["chunks_new"] + answer["chunks_duplicate"] == in_copy,
                f"mid-run upload of {robot.run_id} to node-b: runs {answer['runs']}, {answer['chunks_new']} new + "
                f"{answer['chunks_duplicate']} duplicate chunks; expected [{robot.run_id!r}] and the copy's {in_copy}",
            )
        for run_id in runs:
            expect_owner(problems, b, run_id, "node-a", "while every run is live on node-a")
        for robot in robots:
            robot.go_on()
        for robot in robots:
            robot.expect("STEP 2")

        # 2. A dies with everything it held. With checks every 30 s no agent was told A holds anything
        # (it sends it all again); with checks every second each was told A holds what it sent so far,
        # and must find out that this died with A.
        def status_of(agent: AgentProcess, run_id: str) -> dict[str, Any]:
            (status,) = [r for r in agent.status()["runs"] if r["run"] == run_id]
            return dict(status)

        def told(agent: AgentProcess, run_id: str) -> bool:
            status = status_of(agent, run_id)
            return bool(status["unconfirmed_at_depot_bytes"] < status["local_bytes"])

        if agent_check_s == "1":
            pairs = list(zip(agents, agent_runs, strict=True))
            assert holds_within(lambda: all(told(agent, run_id) for agent, run_id in pairs), 30), (
                "no agent was told node-a holds its chunks"
            )
        for agent, run_id in zip(agents, agent_runs, strict=True):
            status = status_of(agent, run_id)
            assert not status["confirmed"], f"agent of {run_id} had its run confirmed sealed before the kill: {status}"
            assert told(agent, run_id) == (agent_check_s == "1"), f"agent of {run_id} ({agent_check_s} s): {status}"
        a.kill()

        # 3. the robots end: the SDK robots' streams are dead, the agents' go to C
        for robot in robots:
            robot.go_on()
        for robot in robots:
            robot.expect(f"STEP {STEPS}")
            robot.go_on()
        for robot in robots:
            robot.expect("DONE")
            robot.finish()
        for robot in sdk_robots:  # the robot's upload job, once its run has ended
            problems.attempt(
                f"final upload of {robot.run_id}",
                functools.partial(upload, b, robot.copy, robot.token, wait_s=UPLOAD_WAIT_S),
            )
            expect_owner(problems, b, robot.run_id, "node-b", "after its final upload there, node-a dead")

        # 4. every run sealed once, equal to its robot's copy
        settled = wait_settled(cluster, runs, problems, SETTLE_S)
        listed = [r["id"] for r in b.get("/v1/runs", limit=1000).json()["runs"]]
        for run_id in runs:
            problems.check(
                listed.count(run_id) == 1, f"GET /v1/runs on node-b lists {run_id} {listed.count(run_id)} times"
            )
        for k, run_id in enumerate(settled):  # served by B and by C in turn
            node = (b, c)[k % 2]
            problems.attempt(
                f"sealed run {run_id}",
                functools.partial(verify_sealed, cluster, problems, run_id, copies[run_id], node, rerun_bin, tmp_path),
            )
        seen, overlaps = cluster.job_overlaps("retention")
        problems.check(seen > 0, "no retention job ran on any node (job_runs): the overlap check saw nothing")
        problems.check(not overlaps, "retention job runs overlapped across nodes: " + "; ".join(overlaps[:5]))
        problems.check(
            link.grpc_connections()["node-c"] > 0,
            f"the agents never reconnected to node-c through the balancer: {link.grpc_connections()}",
        )
        problems.attempt("GET /v1/nodes on node-b", lambda: check_nodes(b, dead="node-a", alive=("node-b", "node-c")))
        check_logs(cluster, problems)
    finally:
        for proc in [r.proc for r in sdk_robots] + [r.proc for r in agent_robots]:
            if proc.poll() is None:
                proc.kill()
        for agent in agents:
            agent.stop()
        link.close()
    problems.report(cluster, runs)


def check_nodes(node: Node, dead: str, alive: tuple[str, ...]) -> None:
    """The node's `GET /v1/nodes` says `dead` is not alive (once its heartbeat is old) and `alive` are."""

    def seen() -> dict[str, bool]:
        answer = node.get("/v1/nodes")
        assert answer.status_code == 200, f"{answer.status_code} {answer.text[:300]}"
        return {n["id"]: bool(n["alive"]) for n in answer.json()["nodes"]}

    holds_within(lambda: seen().get(dead) is False, 30)
    found = seen()
    assert found.get(dead) is False and all(found.get(n) for n in alive), (
        f"expected {dead} not alive and {', '.join(alive)} alive, got {found}"
    )
