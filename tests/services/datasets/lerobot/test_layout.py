"""The LeRobot writer's files, read back with pyarrow and PyAV against the v3.0 format: the schemas
LeRobot's loader and Rerun's reader depend on, frames on the fps grid, video pts exactly i / fps,
tasks through pandas' index metadata, statistics, and a resumed export giving the same files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from services.datasets.lerobot import layout
from services.datasets.lerobot.writer import LeRobotWriter
from tests.services.datasets.lerobot.episodes import FEATURES, FPS, HEIGHT, WIDTH, episode, grey, state

LENGTHS = (12, 7)


def write(
    root: Path, lengths: tuple[int, ...] = LENGTHS, tasks: tuple[str, ...] = ("pick the box", "place it")
) -> dict[str, Any]:
    writer = LeRobotWriter(root, fps=FPS, features=FEATURES, robot_type="test_bot")
    records, first = [], 0
    for index, length in enumerate(lengths):
        task = tasks[index % len(tasks)]
        records.append(writer.write(episode(index, length, task), first))
        first += length
    return writer.finish(records)


def test_info_and_the_data_files(tmp_path: Path):
    info = write(tmp_path)
    assert info == json.loads((tmp_path / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["fps"] == FPS
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (2, sum(LENGTHS), 2)
    assert list(info["features"]) == [
        "observation.state", "action", "observation.images.front",
        "timestamp", "frame_index", "episode_index", "index", "task_index",
    ]  # fmt: skip
    assert info["features"]["observation.images.front"]["shape"] == [HEIGHT, WIDTH, 3]
    first = 0
    for index, length in enumerate(LENGTHS):
        table = pq.read_table(tmp_path / layout.data_path(index))
        assert table.schema == pa.schema(
            [
                ("observation.state", pa.list_(pa.float32(), 6)),
                ("action", pa.list_(pa.float32(), 6)),
                ("timestamp", pa.float32()),
                ("frame_index", pa.int64()),
                ("episode_index", pa.int64()),
                ("index", pa.int64()),
                ("task_index", pa.int64()),
            ]
        )
        values = np.array(table.column("observation.state").to_pylist(), dtype=np.float32)
        assert np.array_equal(values, state(index, length))
        assert table.column("timestamp").to_pylist() == [np.float32(i / FPS) for i in range(length)]
        assert table.column("index").to_pylist() == list(range(first, first + length))
        assert set(table.column("task_index").to_pylist()) == {index}
        first += length


def test_videos_on_the_grid(tmp_path: Path):
    write(tmp_path)
    for index, length in enumerate(LENGTHS):
        with av.open(str(tmp_path / layout.video_path("observation.images.front", index))) as video:
            stream = video.streams.video[0]
            assert (stream.codec_context.name, stream.width, stream.height) == ("h264", WIDTH, HEIGHT)
            decoded = list(video.decode(stream))
        assert len(decoded) == length
        for i, frame in enumerate(decoded):
            assert frame.pts is not None and frame.time_base is not None
            assert abs(float(frame.pts * frame.time_base) - i / FPS) < 1e-6  # LeRobot allows 1e-4 s
            assert abs(float(frame.to_ndarray(format="rgb24").mean()) - grey(index, i)) < 4  # within codec error


def test_meta_files(tmp_path: Path):
    write(tmp_path)
    tasks = pq.read_table(tmp_path / layout.TASKS_PATH)
    assert tasks.column("__index_level_0__").to_pylist() == ["pick the box", "place it"]
    assert tasks.schema.field("__index_level_0__").type == pa.string()  # Rerun's reader takes Utf8 only
    pandas = json.loads(tasks.schema.metadata[b"pandas"])
    assert pandas["index_columns"] == ["__index_level_0__"]
    episodes = pq.read_table(tmp_path / layout.EPISODES_PATH).to_pylist()
    assert [(e["episode_index"], e["length"], e["dataset_from_index"], e["dataset_to_index"]) for e in episodes] == [
        (0, 12, 0, 12),
        (1, 7, 12, 19),
    ]
    assert episodes[1]["videos/observation.images.front/to_timestamp"] == 0.7
    assert episodes[1]["tasks"] == ["place it"]
    stats = json.loads((tmp_path / layout.STATS_PATH).read_text())
    every = np.concatenate([state(0, 12), state(1, 7)])
    assert np.allclose(stats["observation.state"]["mean"], every.mean(axis=0), atol=1e-5)
    assert np.allclose(stats["observation.state"]["std"], every.std(axis=0), atol=1e-4)
    assert stats["observation.state"]["count"] == [19]
    assert np.array(stats["observation.images.front"]["mean"]).shape == (3, 1, 1)
    assert set(stats["action"]) == {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}


def test_a_resumed_export_writes_the_same_files(tmp_path: Path):
    write(tmp_path / "whole")
    partial = tmp_path / "resumed"
    writer = LeRobotWriter(partial, fps=FPS, features=FEATURES, robot_type="test_bot")
    writer.write(episode(0, LENGTHS[0], "pick the box"), 0)  # then killed
    again = LeRobotWriter(partial, fps=FPS, features=FEATURES, robot_type="test_bot")
    done = again.written()
    assert list(done) == [0]
    records = [*done.values(), again.write(episode(1, LENGTHS[1], "place it"), LENGTHS[0])]
    again.finish(records)
    for name in ("meta/info.json", "meta/stats.json", layout.data_path(0), layout.data_path(1)):
        assert (partial / name).read_bytes() == (tmp_path / "whole" / name).read_bytes(), name
