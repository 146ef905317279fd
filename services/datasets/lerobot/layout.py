"""The files of a LeRobot v3.0 dataset and their exact schemas, as the `lerobot` package (0.4 and
later) writes and reads them.

One data file and one MP4 per camera per episode (`chunk-{episode // 1000}/file-{episode % 1000}`),
so each episode's video starts at 0 in its file. Frames are on a fixed grid: frame i of an episode
has `timestamp = i / fps` and its video frame pts exactly i / fps (LeRobot's loader matches them
within 1e-4 s). `tasks.parquet` carries the pandas index metadata LeRobot reads its task strings
through. Pinned by tests/services/datasets/lerobot/test_layout.py.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000  # files per chunk-XXX folder
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
TASKS_PATH = "meta/tasks.parquet"
INFO_PATH = "meta/info.json"
STATS_PATH = "meta/stats.json"
DEFAULT_FEATURES: dict[str, dict[str, Any]] = {
    "timestamp": {"dtype": "float32", "shape": [1], "names": None},
    "frame_index": {"dtype": "int64", "shape": [1], "names": None},
    "episode_index": {"dtype": "int64", "shape": [1], "names": None},
    "index": {"dtype": "int64", "shape": [1], "names": None},
    "task_index": {"dtype": "int64", "shape": [1], "names": None},
}


def chunk_file(episode: int) -> dict[str, int]:
    return {"chunk_index": episode // CHUNKS_SIZE, "file_index": episode % CHUNKS_SIZE}


def data_path(episode: int) -> str:
    return DATA_PATH.format(**chunk_file(episode))


def video_path(video_key: str, episode: int) -> str:
    return VIDEO_PATH.format(video_key=video_key, **chunk_file(episode))


@dataclass(frozen=True)
class Vector:
    """A float32 vector feature (`observation.state`, `action`): its dimension names."""

    key: str
    names: tuple[str, ...]


@dataclass(frozen=True)
class Camera:
    """A video feature (`observation.images.NAME`): its frame size and how it was encoded."""

    key: str
    height: int
    width: int
    codec: str = "h264"  # as LeRobot's info names it: h264 | av1


@dataclass
class Features:
    vectors: list[Vector] = field(default_factory=list)
    cameras: list[Camera] = field(default_factory=list)

    def info(self, fps: int) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for vector in self.vectors:
            out[vector.key] = {"dtype": "float32", "shape": [len(vector.names)], "names": list(vector.names)}
        for camera in self.cameras:
            out[camera.key] = {
                "dtype": "video",
                "shape": [camera.height, camera.width, 3],
                "names": ["height", "width", "channels"],
                "info": {
                    "video.height": camera.height,
                    "video.width": camera.width,
                    "video.codec": camera.codec,
                    "video.pix_fmt": "yuv420p",
                    "video.is_depth_map": False,
                    "video.fps": fps,
                    "video.channels": 3,
                    "has_audio": False,
                },
            }
        return {**out, **DEFAULT_FEATURES}

    def as_json(self) -> dict[str, Any]:
        """What `from_json` reads back (an export resumed keeps its first episode's features)."""
        return {
            "vectors": [[v.key, list(v.names)] for v in self.vectors],
            "cameras": [[c.key, c.height, c.width, c.codec] for c in self.cameras],
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Features:
        return cls(
            [Vector(key, tuple(names)) for key, names in data["vectors"]],
            [Camera(key, int(height), int(width), codec) for key, height, width, codec in data["cameras"]],
        )


def frames_table(
    vectors: Mapping[str, Any], *, episode: int, first_index: int, task_index: int, fps: int, count: int
) -> pa.Table:
    """An episode's data file: its vectors (n, D) float32, then the five default columns, in the
    order info.json lists them (a column info.json does not declare makes LeRobot refuse the file)."""
    import numpy as np

    columns: dict[str, pa.Array] = {}
    for key, values in vectors.items():
        flat = pa.array(np.ascontiguousarray(values, dtype=np.float32).reshape(-1), pa.float32())
        columns[key] = pa.FixedSizeListArray.from_arrays(flat, int(values.shape[1]))
    frame = np.arange(count, dtype=np.int64)
    columns["timestamp"] = pa.array((frame / fps).astype(np.float32), pa.float32())
    columns["frame_index"] = pa.array(frame, pa.int64())
    columns["episode_index"] = pa.array(np.full(count, episode, dtype=np.int64), pa.int64())
    columns["index"] = pa.array(frame + first_index, pa.int64())
    columns["task_index"] = pa.array(np.full(count, task_index, dtype=np.int64), pa.int64())
    return pa.table(columns)


def tasks_table(tasks: Sequence[str]) -> pa.Table:
    """`meta/tasks.parquet`: LeRobot reads it with pandas and takes a task's text from the index, so
    the file carries pandas' index metadata (written here without pandas)."""
    index = "__index_level_0__"
    pandas_meta = {
        "index_columns": [index],
        "column_indexes": [],
        "columns": [
            {
                "name": "task_index",
                "field_name": "task_index",
                "pandas_type": "int64",
                "numpy_type": "int64",
                "metadata": None,
            },
            {"name": None, "field_name": index, "pandas_type": "unicode", "numpy_type": "object", "metadata": None},
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.0",
    }
    schema = pa.schema(
        [("task_index", pa.int64()), (index, pa.string())], metadata={b"pandas": json.dumps(pandas_meta)}
    )
    return pa.table({"task_index": list(range(len(tasks))), index: list(tasks)}, schema=schema)


def info_json(
    *, fps: int, features: Features, episodes: int, frames: int, tasks: int, robot_type: str | None
) -> dict[str, Any]:
    return {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": robot_type,
        "total_episodes": episodes,
        "total_frames": frames,
        "total_tasks": tasks,
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": 100,
        "video_files_size_in_mb": 200,
        "fps": fps,
        "splits": {"train": f"0:{episodes}"},
        "data_path": DATA_PATH,
        "video_path": VIDEO_PATH if features.cameras else None,
        "features": features.info(fps),
    }


def write_json(path: Path, value: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_suffix(path.suffix + ".tmp")
    temporary.write_text(json.dumps(value, indent=4))
    temporary.replace(path)
