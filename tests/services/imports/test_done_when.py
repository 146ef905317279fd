"""The MCAP issue's scene on a real `fleet serve` with auth on: a ROS 2 bag (Image, PointCloud2, Imu,
TFMessage, String) and a Foxglove protobuf MCAP, written with the real `mcap` libraries, uploaded
with `fleet upload` by a robot's token, converted by the depot, and downloaded as recordings that
`rerun rrd verify` accepts, one entity per topic with every message's value; the bag uploaded twice
is filed once; a corrupt bag is refused with its reason and listed as failed by `fleet imports ls`.
(The agent's own upload of a rosbag2 folder: tests/services/agent/test_bag_uploads.py.)"""

from __future__ import annotations

import json
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.compat import bag_values as V
from tests.compat.bags import FOXGLOVE_EXPECTED, ROS2_EXPECTED, write_foxglove_mcap, write_ros2_bag
from tests.compat.rrd_contents import message_counts, read_rrd, values
from tests.services.imports.mcaps import corrupt
from tests.services.ingest.authed import AuthedDepot
from tests.services.ingest.live_server import FLEET, LiveServer

pytestmark = [pytest.mark.slow, pytest.mark.sdk]
ROBOT = "rover-12"


@pytest.fixture(scope="module")
def depot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AuthedDepot]:
    live = LiveServer(tmp_path_factory.mktemp("done-when") / "data", auth="on", durability="off").start()
    try:
        yield AuthedDepot(live)
    finally:
        live.stop()


def fleet(depot: AuthedDepot, token: str, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "FLEET_API_URL": depot.live.url, "FLEET_TOKEN": token}
    return subprocess.run([FLEET, *args], capture_output=True, text=True, timeout=300, env=env)


def downloaded(depot: AuthedDepot, run_id: str, target: Path, rerun_bin: str) -> Path:
    answer = depot.get(f"/v1/runs/{run_id}/recording.rrd")
    assert answer.status_code == 200, answer.text
    target.write_bytes(answer.content)
    verified = subprocess.run([rerun_bin, "rrd", "verify", str(target)], capture_output=True, text=True, timeout=120)
    assert verified.returncode == 0, verified.stdout + verified.stderr
    return target


def test_bags_upload_convert_and_download_as_verified_recordings(
    depot: AuthedDepot, tmp_path: Path, rerun_bin: str
) -> None:
    robot = depot.token("ingest", robot=ROBOT).token
    bag = write_ros2_bag(tmp_path / "patrol_2026_11_29", messages=6)
    mcap = bag / "patrol_2026_11_29_0.mcap"
    sent = fleet(depot, robot, "upload", str(mcap), "--run-id", "patrol-2026-11-29", "--application", "rosbag2")
    assert sent.returncode == 0, sent.stderr
    assert "MCAP converted" in sent.stdout and "patrol-2026-11-29" in sent.stdout

    chunks = read_rrd(downloaded(depot, "patrol-2026-11-29", tmp_path / "patrol.rrd", rerun_bin))
    counts = message_counts(chunks)
    assert {topic: counts.get(topic) for topic in V.ROS2_TOPICS} == dict.fromkeys(V.ROS2_TOPICS, 6)
    for topic, want in ROS2_EXPECTED.items():
        assert values(chunks, topic, want.component) == [want.row(i) for i in range(6)], topic
    run = depot.run("patrol-2026-11-29")
    assert run is not None and (run["robot_id"], run["application_id"]) == (ROBOT, "rosbag2")

    again = fleet(depot, robot, "upload", str(mcap), "--run-id", "patrol-2026-11-29")
    assert again.returncode == 0 and "already held" in again.stdout, again.stdout + again.stderr
    run_again = depot.run("patrol-2026-11-29")
    assert run_again is not None and run_again["chunks"] == run["chunks"]

    foxglove = write_foxglove_mcap(tmp_path / "dock.mcap")
    sent = fleet(depot, depot.admin, "upload", str(foxglove), "--run-id", "dock-1")
    assert sent.returncode == 0, sent.stderr
    chunks = read_rrd(downloaded(depot, "dock-1", tmp_path / "dock.rrd", rerun_bin))
    counts = message_counts(chunks)
    assert {t: counts.get(t) for t in V.FOXGLOVE_TOPICS} == dict.fromkeys(V.FOXGLOVE_TOPICS, V.FOXGLOVE_MESSAGES)
    for topic, want in FOXGLOVE_EXPECTED.items():
        assert values(chunks, topic, want.component) == [want.row(i) for i in range(V.FOXGLOVE_MESSAGES)], topic
    dock = depot.run("dock-1")
    assert dock is not None and dock["robot_id"] == V.DEVICE_NAME  # the file's foxglove metadata names it


def test_a_corrupt_bag_is_refused_with_its_reason_and_listed_as_failed(depot: AuthedDepot, tmp_path: Path) -> None:
    robot = depot.token("ingest", robot=ROBOT).token
    bag = write_ros2_bag(tmp_path / "broken", messages=40, chunk_size=2048)
    bad = corrupt(bag / "broken_0.mcap", tmp_path / "broken_0.mcap")
    sent = fleet(depot, robot, "upload", str(bad))
    assert sent.returncode == 1 and "is corrupt" in sent.stderr, sent.stdout + sent.stderr
    listed = fleet(depot, depot.admin, "imports", "ls", "--state", "failed", "--json")
    assert listed.returncode == 0, listed.stderr
    failed = [i for i in json.loads(listed.stdout)["imports"] if i["name"] == "broken_0.mcap"]
    assert len(failed) == 1 and "is corrupt" in failed[0]["reason"] and failed[0]["quarantined"]
    assert depot.live.healthy()
