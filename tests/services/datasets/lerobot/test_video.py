"""The episode video writer: AV1 encoding leaves no thread of the process under real-time
scheduling (SVT-AV1 run as root asks for SCHED_FIFO 99 for its threads and the caller's)."""

from __future__ import annotations

import os
from pathlib import Path

import av
import numpy as np
import pytest

from services.datasets.lerobot.video import VideoWriter

REALTIME = (os.SCHED_FIFO, os.SCHED_RR)


def realtime_threads() -> list[int]:
    found = []
    for tid in os.listdir("/proc/self/task"):
        try:
            if os.sched_getscheduler(int(tid)) in REALTIME:
                found.append(int(tid))
        except OSError:  # the thread ended
            continue
    return found


def can_ask_for_realtime() -> bool:
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except OSError:
        return False
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return True


pytestmark = pytest.mark.skipif(
    not hasattr(os, "sched_getscheduler") or not can_ask_for_realtime(),
    reason="the encoder only gets real-time threads where the process may ask for them (root, CAP_SYS_NICE)",
)


def frame(n: int) -> np.ndarray:
    rgb = np.zeros((64, 96, 3), dtype=np.uint8)
    rgb[:, :, 0] = n * 10
    return rgb


def test_an_av1_episode_is_encoded_without_real_time_threads(tmp_path: Path):
    writer = VideoWriter(tmp_path / "episode.mp4", fps=10, width=96, height=64, codec="av1")
    for n in range(12):
        writer.add(frame(n))
        assert realtime_threads() == [], f"real-time threads after frame {n}"
    writer.close()
    assert realtime_threads() == []
    with av.open(str(tmp_path / "episode.mp4")) as container:
        assert sum(1 for _ in container.decode(video=0)) == 12
