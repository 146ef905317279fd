"""The whole path of issue 32 on a small hidden fleet (auth on, the real rerun-sdk): two robots' runs
with an intervention each, a snapshot of "5 s before each intervention" on both robots, exported
from the command line as LeRobot v3.0; its values equal the source recordings at the sampled times;
re-exported, its data files are byte-identical; the real `lerobot` loads it; deleting a used run is
refused naming the snapshot."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import rerun as rr

from sdk_client.rest import ServiceError
from services.cli.dataset_exports import export_here
from services.datasets.export import ExportSpec
from services.datasets.lerobot import layout
from services.datasets.quality import Limits
from tests.compat.lerobot_venv import lerobot_python
from tests.services.auth.conftest import Depot, bearer
from tests.services.datasets.conftest import sdk

S = 1_000_000_000
START = 1_790_000_000 * S
TICKS = 90  # 9 s at 10 Hz
TAKEOVER = 70  # the intervention at 7 s: the window is [2 s, 7 s]
ROBOTS = {"robot-7": 1.0, "robot-9": -1.0}  # each robot's joints run its own way
CHECK = str(Path(__file__).parent / "lerobot" / "lerobot_check.py")
SPEC = ExportSpec(("/joints",), ("/cmd",), (("/camera/front", "observation.images.front"),), "take over safely", 10)


def joints(robot: str, i: int) -> list[float]:
    sign = ROBOTS[robot]
    return [sign * i, sign * 2.0 * i, 0.5 * i]


def drive(path: Path, robot: str, run_id: str) -> bytes:
    rec = rr.RecordingStream("takeover_test", recording_id=run_id)
    rec.save(str(path))
    rec.send_property("fleet", rr.AnyValues(robot_id=robot))
    for i in range(TICKS):
        rec.set_time("sim_time", timestamp=np.datetime64(START + i * S // 10, "ns"))
        rec.log("/joints", rr.Scalars(joints(robot, i)))
        rec.log("/cmd", rr.Scalars([v + 0.25 for v in joints(robot, i)]))
        rec.log("/camera/front", rr.Image(np.full((24, 32, 3), (i * 7) % 200 + 20, dtype=np.uint8)))
        rec.log("/noise", rr.Scalars([float(i)]))  # logged, not exported
    rec.flush()
    rec.disconnect()
    return path.read_bytes()


def fleet(depot: Depot, tmp_path: Path) -> dict[str, str]:
    """Each robot's run, uploaded by the robot, with its operator's intervention annotated."""
    runs = {}
    people = sdk(depot, depot.token("write", name="operator"))
    for robot in ROBOTS:
        run_id = f"run-{robot}"
        data = drive(tmp_path / f"{run_id}.rrd", robot, run_id)
        sent = depot.client.post("/v1/uploads", content=data, headers=bearer(depot.token("ingest", robot=robot)))
        assert sent.status_code == 200, sent.text
        at = START + TAKEOVER * S // 10
        people.annotate(run_id, "sim_time", str(at), end=str(at), kind="intervention", label="took over")
        sealed = depot.client.post(f"/v1/runs/{run_id}/promote", headers=bearer(depot.token("write")))
        assert sealed.status_code == 200 and sealed.json()["tier"] == "warm", sealed.text
        runs[robot] = run_id
    return runs


def test_five_seconds_before_each_intervention_on_two_robots(depot: Depot, tmp_path: Path):
    runs = fleet(depot, tmp_path)
    alice = sdk(depot, depot.token("write", name="alice"))
    made = alice.create_dataset(
        "takeovers",
        robot=list(ROBOTS),
        event_window={"event": ["intervention"], "before_s": 5, "after_s": 0},
        include=["/joints", "/cmd", "/camera/**"],
        timeline="sim_time",
        fps=10,
    )
    assert (made["ref"], made["episodes"], made["runs"]) == ("takeovers@1", 2, 2)

    first = export_here(alice, "takeovers", 1, SPEC, tmp_path / "one", Limits(), strict=True)  # no flag: sealed runs
    assert first.info is not None and first.info["total_episodes"] == 2
    frames = TAKEOVER - (TAKEOVER - 50) + 1  # [2 s, 7 s] at 10 fps: 51 frames
    assert first.info["total_frames"] == 2 * frames
    for index, robot in enumerate(sorted(ROBOTS, key=lambda r: runs[r])):
        table = pq.read_table(tmp_path / "one" / layout.data_path(index))
        state = np.array(table.column("observation.state").to_pylist())
        action = np.array(table.column("action").to_pylist())
        ticks = range(TAKEOVER - 50, TAKEOVER + 1)  # the source's rows at the sampled times
        assert np.allclose(state, [joints(robot, i) for i in ticks])
        assert np.allclose(action, state + 0.25)
    assert first.info["features"]["observation.state"]["names"] == ["/joints[0]", "/joints[1]", "/joints[2]"]

    again = export_here(alice, "takeovers", 1, SPEC, tmp_path / "two", Limits(), strict=False)
    assert again.info == first.info
    for name in (layout.data_path(0), layout.data_path(1), layout.INFO_PATH, layout.STATS_PATH, layout.TASKS_PATH):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes(), name

    with pytest.raises(ServiceError) as refused:
        sdk(depot, depot.token("admin")).delete_run(runs["robot-7"])
    assert refused.value.status == 409 and "takeovers@1" in str(refused.value)


@pytest.mark.slow
def test_the_real_lerobot_loads_the_takeovers(depot: Depot, tmp_path: Path):
    fleet(depot, tmp_path)
    alice = sdk(depot, depot.token("write", name="alice"))
    alice.create_dataset(
        "takeovers",
        robot=list(ROBOTS),
        event_window={"event": ["intervention"], "before_s": 5},
        timeline="sim_time",
        fps=10,
    )
    export_here(alice, "takeovers", 1, SPEC, tmp_path / "out", Limits(), strict=False)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf-home")}
    done = subprocess.run(
        [str(lerobot_python()), CHECK, str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    *_, summary = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    assert summary == {"total": 2 * 51, "episodes": 2, "fps": 10}
