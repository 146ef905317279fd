"""A snapshot version exported as a LeRobot dataset: a robot's run (the real SDK: joints, commands
and a camera at 10 Hz on a timestamp timeline) uploaded, a snapshot made of it, exported at 10 fps.
Every frame's state and action equal the source's latest values at its grid time; its video frame
decodes to the source image within codec error; the real `lerobot` loads it; an export resumed
after its first episode writes the same files."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import av
import numpy as np
import pyarrow.parquet as pq
import pytest
import rerun as rr

from services.datasets.episodes import export_version
from services.datasets.export import ExportSpec
from services.datasets.lerobot import layout
from services.datasets.resolve import Sources
from tests.compat.lerobot_venv import lerobot_python
from tests.services.auth.conftest import Depot, bearer
from tests.services.datasets.conftest import ROBOT, writer

S = 1_000_000_000
START = 1_790_000_000 * S
FRAMES = 30  # 3 s at 10 Hz
CHECK = str(Path(__file__).parent / "lerobot" / "lerobot_check.py")
SPEC = ExportSpec(("/joints",), ("/cmd",), (("/camera/front", "observation.images.front"),), "pick the box", 10)


def joints(i: int) -> list[float]:
    return [i * 1.0, i * 2.0, -i * 0.5]


def grey(i: int) -> int:
    return (i * 29) % 200 + 20


def drive(path: Path, run_id: str) -> bytes:
    rec = rr.RecordingStream("export_test", recording_id=run_id)
    rec.save(str(path))
    rec.send_property("fleet", rr.AnyValues(robot_id=ROBOT))
    for i in range(FRAMES):
        rec.set_time("sim_time", timestamp=np.datetime64(START + i * S // 10, "ns"))
        rec.log("/joints", rr.Scalars(joints(i)))
        rec.log("/cmd", rr.Scalars([v + 0.25 for v in joints(i)]))
        rec.log("/camera/front", rr.Image(np.full((24, 32, 3), grey(i), dtype=np.uint8)))
    rec.flush()
    rec.disconnect()
    return path.read_bytes()


def snapshot(depot: Depot, tmp_path: Path, run_ids: list[str]) -> None:
    for run_id in run_ids:
        data = drive(tmp_path / f"{run_id}.rrd", run_id)
        answer = depot.client.post("/v1/uploads", content=data, headers=bearer(depot.token("ingest", robot=ROBOT)))
        assert answer.status_code == 200, answer.text
    made = writer(depot).create_dataset("drives", robot=[ROBOT], timeline="sim_time", fps=10)
    assert made["episodes"] == len(run_ids)


def sources(depot: Depot) -> Sources:
    state = depot.app.state
    return Sources(state.catalog, state.node.tiers.warm, state.ingest, state.node.clock)


def test_frames_equal_the_source_at_their_grid_times(depot: Depot, tmp_path: Path):
    snapshot(depot, tmp_path, ["run-a", "run-b"])
    root = tmp_path / "export"
    info = export_version(sources(depot), "drives", 1, SPEC, root).info
    assert info is not None
    assert (info["total_episodes"], info["total_frames"]) == (2, 2 * FRAMES)
    assert info["features"]["observation.state"]["names"] == ["/joints[0]", "/joints[1]", "/joints[2]"]
    for episode in (0, 1):
        table = pq.read_table(root / layout.data_path(episode))
        state = np.array(table.column("observation.state").to_pylist())
        action = np.array(table.column("action").to_pylist())
        assert np.allclose(state, [joints(i) for i in range(FRAMES)])
        assert np.allclose(action, state + 0.25)
        with av.open(str(root / layout.video_path("observation.images.front", episode))) as video:
            means = [f.to_ndarray(format="rgb24").mean() for f in video.decode(video.streams.video[0])]
        assert len(means) == FRAMES
        assert all(abs(m - grey(i)) < 4 for i, m in enumerate(means))


def test_an_export_at_a_higher_rate_repeats_the_latest_sample(depot: Depot, tmp_path: Path):
    snapshot(depot, tmp_path, ["run-c"])
    root = tmp_path / "export"
    info = export_version(sources(depot), "drives", 1, ExportSpec(("/joints",), (), (), "t", 20), root).info
    assert info is not None
    assert info["total_frames"] == 2 * FRAMES - 1  # 0.0, 0.05, ..., 2.9 s
    state = np.array(pq.read_table(root / layout.data_path(0)).column("observation.state").to_pylist())
    assert np.allclose(state, [joints(k // 2) for k in range(2 * FRAMES - 1)])


def test_a_resumed_export_writes_the_same_files(depot: Depot, tmp_path: Path):
    snapshot(depot, tmp_path, ["run-d", "run-e"])
    export_version(sources(depot), "drives", 1, SPEC, tmp_path / "whole")
    partial = tmp_path / "resumed"

    class Killed(Exception):
        pass

    def kill_after_first(progress: object) -> None:
        raise Killed

    with pytest.raises(Killed):
        export_version(sources(depot), "drives", 1, SPEC, partial, kill_after_first)
    assert not (partial / layout.INFO_PATH).exists()
    export_version(sources(depot), "drives", 1, SPEC, partial)
    for name in (layout.INFO_PATH, layout.STATS_PATH, layout.data_path(0), layout.data_path(1)):
        assert (partial / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name


@pytest.mark.slow
def test_lerobot_loads_the_export(depot: Depot, tmp_path: Path):
    snapshot(depot, tmp_path, ["run-f", "run-g"])
    root = tmp_path / "export"
    export_version(sources(depot), "drives", 1, SPEC, root)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf-home")}
    done = subprocess.run(
        [str(lerobot_python()), CHECK, str(root)], capture_output=True, text=True, timeout=600, env=env, check=False
    )
    assert done.returncode == 0, done.stderr[-3000:]
    *frames, summary = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    assert summary == {"total": 2 * FRAMES, "episodes": 2, "fps": 10}
    for f in frames:
        assert f["missing"] == [] and f["task"] == "pick the box"
        assert np.allclose(f["state"], joints(f["frame"])) and np.allclose(
            f["action"], np.add(joints(f["frame"]), 0.25)
        )
        assert abs(f["images"]["observation.images.front"] - grey(f["frame"])) < 4


def test_an_av1_export_decodes_to_the_source_images(depot: Depot, tmp_path: Path):
    snapshot(depot, tmp_path, ["run-h"])
    root = tmp_path / "av1"
    spec = ExportSpec(("/joints",), (), (("/camera/front", "observation.images.front"),), "t", 10, "av1")
    info = export_version(sources(depot), "drives", 1, spec, root).info
    assert info is not None and info["features"]["observation.images.front"]["info"]["video.codec"] == "av1"
    with av.open(str(root / layout.video_path("observation.images.front", 0))) as video:
        stream = video.streams.video[0]
        assert stream.codec_context.name in ("libdav1d", "av1", "libaom-av1")
        means = [f.to_ndarray(format="rgb24").mean() for f in video.decode(stream)]
    assert len(means) == FRAMES and all(abs(m - grey(i)) < 4 for i, m in enumerate(means))
