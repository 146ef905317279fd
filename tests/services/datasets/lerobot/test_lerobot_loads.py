"""The real `lerobot` package (its own cached venv: tests/compat/lerobot_venv.py) loads what the
writer makes: every frame, its values, its decoded video frame within codec error, its task."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from services.datasets.lerobot.writer import LeRobotWriter
from tests.compat.lerobot_venv import lerobot_python
from tests.services.datasets.lerobot.episodes import FEATURES, FPS, HEIGHT, WIDTH, episode, grey, state

pytestmark = [pytest.mark.slow]

CHECK = str(Path(__file__).with_name("lerobot_check.py"))
LENGTHS = (15, 8, 11)
TASKS = ("pick the box", "place it", "pick the box")


def test_lerobot_loads_every_frame(tmp_path: Path):
    root = tmp_path / "export"
    writer = LeRobotWriter(root, fps=FPS, features=FEATURES, robot_type="test_bot")
    records, first = [], 0
    for index, length in enumerate(LENGTHS):
        records.append(writer.write(episode(index, length, TASKS[index]), first))
        first += length
    writer.finish(records)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HOME": str(tmp_path / "hf-home")}
    done = subprocess.run(
        [str(lerobot_python()), CHECK, str(root)], capture_output=True, text=True, timeout=600, env=env, check=False
    )
    assert done.returncode == 0, done.stderr[-3000:]
    *frames, summary = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    assert summary == {"total": sum(LENGTHS), "episodes": len(LENGTHS), "fps": FPS}
    assert [(f["episode"], f["frame"]) for f in frames] == [(e, i) for e, n in enumerate(LENGTHS) for i in range(n)]
    for f in frames:
        expected = state(f["episode"], LENGTHS[f["episode"]])[f["frame"]]
        assert f["missing"] == []
        assert np.allclose(f["state"], expected) and np.allclose(f["action"], expected + 0.5)
        assert abs(f["timestamp"] - f["frame"] / FPS) < 1e-6
        assert f["shapes"] == {"observation.images.front": [3, HEIGHT, WIDTH]}
        assert abs(f["images"]["observation.images.front"] - grey(f["episode"], f["frame"])) < 4
        assert f["task"] == TASKS[f["episode"]]
    assert [f["index"] for f in frames] == list(range(sum(LENGTHS)))
