"""Writing a LeRobot v3.0 dataset episode by episode, resumable: an episode's data file and videos
are each written beside and renamed, then its record (`.export/episode-NNNNNN.json`: length, task,
statistics); an export killed midway starts again after the last recorded episode. `finish` writes
the `meta/` files from the records, so the same episodes always give the same files."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from services.datasets.lerobot import layout, stats
from services.datasets.lerobot.video import write_video

PROGRESS_DIR = ".export"
IMAGE_STATS_FRAMES = 100  # frames of each camera an episode's image statistics are taken from


@dataclass
class Episode:
    """One episode on the grid: `length` frames; vectors (length, D) float32; camera frames
    (H, W, 3) uint8, exactly `length` of each."""

    index: int
    task: str
    length: int
    vectors: Mapping[str, np.ndarray]
    cameras: Mapping[str, Iterable[np.ndarray]] = field(default_factory=dict)
    # what the record says of where the episode came from, asked once its videos are written
    describe: Callable[[], Mapping[str, Any]] | None = None


class LeRobotWriter:
    def __init__(
        self, root: Path, *, fps: int, features: layout.Features, codec: str = "h264", robot_type: str | None = None
    ) -> None:
        self.root, self.fps, self.features, self.codec, self.robot_type = root, fps, features, codec, robot_type
        self.progress = root / PROGRESS_DIR
        self.progress.mkdir(parents=True, exist_ok=True)
        self.tasks: list[str] = []  # in the order episodes first name them: a task's index is its place

    def _record_path(self, episode: int) -> Path:
        return self.progress / f"episode-{episode:06d}.json"

    def written(self) -> dict[int, dict[str, Any]]:
        """The episodes already written (an export resumed after a kill)."""
        out: dict[int, dict[str, Any]] = {}
        for path in sorted(self.progress.glob("episode-*.json")):
            record = json.loads(path.read_text())
            out[int(record["episode_index"])] = record
            if record["task"] not in self.tasks:
                self.tasks.append(record["task"])
        return out

    def write(self, episode: Episode, first_index: int) -> dict[str, Any]:
        """Write one episode's files (episodes in order, each after those before it); its record."""
        if episode.task not in self.tasks:
            self.tasks.append(episode.task)
        task_index = self.tasks.index(episode.task)
        table = layout.frames_table(
            episode.vectors,
            episode=episode.index,
            first_index=first_index,
            task_index=task_index,
            fps=self.fps,
            count=episode.length,
        )
        path = self.root / layout.data_path(episode.index)
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary = path.with_suffix(".parquet.tmp")
        pq.write_table(table, temporary, compression="snappy")
        temporary.replace(path)
        feature_stats = {key: stats.vector_stats(np.asarray(values)) for key, values in episode.vectors.items()}
        every = max(episode.length // IMAGE_STATS_FRAMES, 1)
        for camera in self.features.cameras:
            sample: list[np.ndarray] = []
            frames = _sampled(episode.cameras[camera.key], every, sample)
            count = write_video(
                self.root / layout.video_path(camera.key, episode.index), frames, fps=self.fps, codec=self.codec
            )
            if count != episode.length:
                raise ValueError(f"camera {camera.key}: {count} frames for an episode of {episode.length}")
            feature_stats[camera.key] = stats.image_stats(np.stack(sample))
        for column in ("timestamp", "frame_index", "episode_index", "index", "task_index"):
            feature_stats[column] = stats.vector_stats(table.column(column).to_numpy())
        record = {
            "episode_index": episode.index,
            "task": episode.task,
            "length": episode.length,
            "first_index": first_index,
            "stats": stats.as_json(feature_stats),
            "source": dict(episode.describe()) if episode.describe is not None else None,
        }
        layout.write_json(self._record_path(episode.index), record)
        return record

    def finish(self, records: Iterable[Mapping[str, Any]]) -> dict[str, Any]:
        """The `meta/` files from every episode's record; info.json's contents."""
        ordered = sorted(records, key=lambda r: int(r["episode_index"]))
        tasks = list(dict.fromkeys(str(r["task"]) for r in ordered))
        (self.root / "meta").mkdir(parents=True, exist_ok=True)
        pq.write_table(layout.tasks_table(tasks), self.root / layout.TASKS_PATH)
        self._episodes_table(ordered)
        per_feature: dict[str, list[stats.Stats]] = {}
        for record in ordered:
            for feature, values in record["stats"].items():
                per_feature.setdefault(feature, []).append({k: np.asarray(v) for k, v in values.items()})
        layout.write_json(
            self.root / layout.STATS_PATH,
            stats.as_json({feature: stats.aggregate(held) for feature, held in per_feature.items()}),
        )
        info = layout.info_json(
            fps=self.fps,
            features=self.features,
            episodes=len(ordered),
            frames=sum(int(r["length"]) for r in ordered),
            tasks=len(tasks),
            robot_type=self.robot_type,
        )
        layout.write_json(self.root / layout.INFO_PATH, info)
        return info

    def _episodes_table(self, records: list[Mapping[str, Any]]) -> None:
        columns: dict[str, list[Any]] = {
            "episode_index": [int(r["episode_index"]) for r in records],
            "tasks": [[str(r["task"])] for r in records],
            "length": [int(r["length"]) for r in records],
            "data/chunk_index": [layout.chunk_file(int(r["episode_index"]))["chunk_index"] for r in records],
            "data/file_index": [layout.chunk_file(int(r["episode_index"]))["file_index"] for r in records],
            "dataset_from_index": [int(r["first_index"]) for r in records],
            "dataset_to_index": [int(r["first_index"]) + int(r["length"]) for r in records],
        }
        for camera in self.features.cameras:
            prefix = f"videos/{camera.key}"
            columns[f"{prefix}/chunk_index"] = columns["data/chunk_index"]
            columns[f"{prefix}/file_index"] = columns["data/file_index"]
            columns[f"{prefix}/from_timestamp"] = [0.0 for _ in records]
            columns[f"{prefix}/to_timestamp"] = [int(r["length"]) / self.fps for r in records]
        for feature in records[0]["stats"] if records else ():
            for key in stats.KEYS:
                columns[f"stats/{feature}/{key}"] = [r["stats"][feature][key] for r in records]
        columns["meta/episodes/chunk_index"] = [0 for _ in records]
        columns["meta/episodes/file_index"] = [0 for _ in records]
        path = self.root / layout.EPISODES_PATH
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pydict(columns), path)


def _sampled(frames: Iterable[np.ndarray], every: int, sample: list[np.ndarray]) -> Iterable[np.ndarray]:
    """`frames` passed on, every `every`-th kept in `sample` (at most IMAGE_STATS_FRAMES)."""
    for i, rgb in enumerate(frames):
        if i % every == 0 and len(sample) < IMAGE_STATS_FRAMES:
            sample.append(stats.stats_sample(rgb))
        yield rgb
