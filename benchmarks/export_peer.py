"""The peer of benchmarks/export.py, run by the cached lerobot venv's python: the same episodes written
by LeRobot's own writer (`LeRobotDataset.create`, `add_frame`, `save_episode`, `finalize`), its frames
and values made by the same formulas (`benchmarks/export_frames.py`, loaded by path), no decoding.

    python benchmarks/export_peer.py ROOT EPISODES FRAMES FPS WIDTH HEIGHT CODEC

Prints one JSON line: wall seconds, CPU seconds, peak RSS in MB (this process).
"""

from __future__ import annotations

import importlib.util
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # type: ignore[import-not-found]

spec = importlib.util.spec_from_file_location("export_frames", Path(__file__).with_name("export_frames.py"))
assert spec is not None and spec.loader is not None
frames = importlib.util.module_from_spec(spec)
spec.loader.exec_module(frames)


def main() -> None:
    root, episodes, count, fps, width, height, codec = sys.argv[1:8]
    n, length, rate, w, h = int(episodes), int(count), int(fps), int(width), int(height)
    started, cpu0 = time.perf_counter(), time.process_time()
    features = {
        "observation.state": {"dtype": "float32", "shape": (frames.JOINTS,), "names": None},
        "action": {"dtype": "float32", "shape": (frames.JOINTS,), "names": None},
        "observation.images.front": {"dtype": "video", "shape": (h, w, 3), "names": ["height", "width", "channels"]},
    }
    dataset = LeRobotDataset.create("bench/peer", rate, features, root=root, use_videos=True, vcodec=codec)
    for episode in range(n):
        for i in range(length):
            tick = i * frames.SCALAR_HZ // rate  # the scalar row latest at the frame's time
            dataset.add_frame(
                {
                    "observation.state": np.asarray(frames.joints(episode, tick), dtype=np.float32),
                    "action": np.asarray(frames.command(episode, tick), dtype=np.float32),
                    "observation.images.front": frames.image(i * frames.CAMERA_HZ // rate, w, h),
                    "task": "bench",
                }
            )
        dataset.save_episode()
    dataset.finalize()
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6
    print(
        json.dumps({"wall_s": time.perf_counter() - started, "cpu_s": time.process_time() - cpu0, "peak_mb": peak_mb})
    )


if __name__ == "__main__":
    main()
