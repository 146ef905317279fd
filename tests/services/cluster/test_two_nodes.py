"""Two nodes on one catalog and bucket, no failure: a robot streams its run live to node A with the
real SDK; its FileSink copy, as it stands mid-run, is uploaded to node B. B files the upload through
the run's owner (the answer counts every chunk, new or duplicate), says A owns the run while it is
hot, and the run is sealed once, by its owner, equal to the robot's copy; neither node logs an error."""

from __future__ import annotations

import functools
from pathlib import Path

import pytest

from tests.services.cluster.harness import (
    Cluster,
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

RUN, ROBOT = "pair-run-1", "robot-pair"
SETTLE_S = 90  # the robot's end, FLEET_PROMOTE_AFTER_S, a promotion pass: seconds, on a busy machine more


def test_an_upload_to_another_node_is_filed_with_the_runs_owner(cluster: Cluster, tmp_path: Path, rerun_bin: str):
    a, b = cluster.add("node-a"), cluster.add("node-b")
    cluster.start("node-a", "node-b")
    token = cluster.ingest_token(ROBOT)
    copy = tmp_path / f"{RUN}.rrd"
    robot = SdkRobot(a.grpc_url, copy, RUN, ROBOT, token, steps=2, frames=15)
    problems = Problems()
    try:
        robot.expect("STEP 1")  # flushed: node A has the first half, the copy holds it too
        # Asked of node-b, which answers from the catalog alone (node-a answers its hot run from
        # ingest's view before its catalog flush): the run is filed.
        assert holds_within(lambda: (b.run(RUN) or {}).get("chunks", 0) > 0, 30), (
            f"the catalog never showed run {RUN}\n{cluster.diagnosis([RUN])}"
        )
        in_copy = len(chunks_in(copy))
        answer = upload(b, copy, token)
        problems.check(answer["runs"] == [RUN], f"upload to node-b answered runs {answer['runs']}, expected [{RUN!r}]")
        problems.check(
            answer["chunks_new"] + answer["chunks_duplicate"] == in_copy,
            f"upload of the mid-run copy to node-b filed {answer['chunks_new']} new + {answer['chunks_duplicate']} "
            f"duplicate chunks, expected the copy's {in_copy}",
        )
        expect_owner(problems, b, RUN, "node-a", "while the run is live on node-a")
        robot.go_on()
        robot.expect("STEP 2")
        robot.go_on()
        robot.expect("DONE")
        robot.finish()
        if wait_settled(cluster, [RUN], problems, SETTLE_S):
            sealed = functools.partial(verify_sealed, cluster, problems, RUN, copy, b, rerun_bin, tmp_path)
            problems.attempt(f"sealed run {RUN}", sealed)
        check_logs(cluster, problems)
    finally:
        robot.kill()
    problems.report(cluster, [RUN])
