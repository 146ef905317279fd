"""Run by the `lerobot` venv's python (not this project's): load a dataset with the real
`LeRobotDataset` and print every frame as a JSON line (episode, frame, timestamp, state, action,
the mean of each camera's decoded image, task), then one line with the dataset's figures.

    python lerobot_check.py ROOT
"""

import json
import sys

from lerobot.datasets.lerobot_dataset import LeRobotDataset  # type: ignore[import-not-found]  # its own venv

root = sys.argv[1]
dataset = LeRobotDataset("local/export", root=root, video_backend="pyav")
cameras = list(dataset.meta.video_keys)
for i in range(len(dataset)):
    item = dataset[i]
    missing = [key for key, value in item.items() if value is None]
    line = {
        "index": int(item["index"]),
        "episode": int(item["episode_index"]),
        "frame": int(item["frame_index"]),
        "timestamp": float(item["timestamp"]),
        "state": item["observation.state"].tolist(),
        "action": item["action"].tolist(),
        "images": {key: float(item[key].mean()) * 255 for key in cameras},
        "shapes": {key: list(item[key].shape) for key in cameras},
        "task": item["task"],
        "missing": missing,
    }
    print(json.dumps(line))
print(json.dumps({"total": len(dataset), "episodes": dataset.meta.total_episodes, "fps": dataset.meta.fps}))
