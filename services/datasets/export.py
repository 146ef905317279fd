"""A snapshot version exported as a LeRobot v3.0 dataset: each episode's chunks read from its run
(hot or sealed, by ranged reads of the chunks the version lists), resampled onto a fixed grid of
`fps` frames per second by latest-at (as Rerun's own exporter does), and written by the LeRobot
writer episode by episode, so an export killed midway resumes after its last written episode.

The grid of an episode runs over its window (a whole-run episode: from the first to the last sample
of its observation and action entities), on the snapshot's timeline, which must count time
(timestamp or duration). Frames before every feature has a first sample are left out. The
observation vector is the observation entities' scalars in entity-path order, each entity's
instances in their order; the action vector likewise; each camera a video feature.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from catalog import datasets as queries
from catalog.db import session_scope
from catalog.models import DatasetEpisode
from core.errors import BadParameterError, ConflictError, NotFoundError
from services.datasets.lerobot.layout import Camera, Features, Vector
from services.datasets.lerobot.writer import Episode, LeRobotWriter
from services.datasets.resolve import RunRef, Skipped, Sources, open_run
from services.datasets.samples import Series, read_series
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.messages import ArrowMessage
from services.runs.download import EntityFilter
from services.runs.indexed import read_events

NS = 1_000_000_000
TIME_TYPES = ("timestamp", "duration")


@dataclass(frozen=True)
class ExportSpec:
    """What goes where: entity patterns for the state and the action, cameras as (entity, feature
    key), the task text, the rate and the video codec."""

    observation: tuple[str, ...]
    action: tuple[str, ...]
    cameras: tuple[tuple[str, str], ...] = ()
    task: str = ""
    fps: int = 10
    codec: str = "h264"

    def check(self) -> None:
        if not 1 <= self.fps <= 1000:
            raise BadParameterError("fps", f"{self.fps}: a whole number of frames per second, 1 to 1000")
        if not self.observation and not self.action and not self.cameras:
            raise BadParameterError("observation", "name what to export: --observation, --action or --camera")
        for entity, key in self.cameras:
            if not key.startswith("observation.images.") or "/" in key:
                raise BadParameterError("camera", f"{entity}={key}: the feature is observation.images.NAME")


def matches(patterns: Sequence[str], path: str) -> bool:
    return bool(patterns) and EntityFilter(list(patterns))(path)


@dataclass
class Progress:
    episodes: int
    done: int = 0
    frames: int = 0


def export_version(
    sources: Sources,
    name: str,
    version: int,
    spec: ExportSpec,
    root: Path,
    progress: Callable[[Progress], None] | None = None,
) -> dict[str, Any]:
    """Write NAME@VERSION under `root` (resuming an export there); info.json's contents."""
    spec.check()
    with session_scope(sources.catalog) as session:
        row = queries.version(session, name, version)
        if row is None:
            raise NotFoundError(f"no dataset version {queries.ref(name, version)}: `fleet datasets show {name}`")
        episodes = queries.episodes(session, name, version, -1, 10**9)
        session.expunge_all()
    writer: LeRobotWriter | None = None
    records: list[dict[str, Any]] = []
    state = Progress(len(episodes))
    first = 0
    for episode in episodes:
        series = _episode_series(sources, episode, spec)
        if writer is None:
            writer = LeRobotWriter(root, fps=spec.fps, features=_features(series, spec), codec=spec.codec)
            done = writer.written()
        if episode.episode in done:
            record = done[episode.episode]
        else:
            record = writer.write(_on_grid(episode, series, spec, writer.features), first)
        records.append(record)
        first += int(record["length"])
        state.done, state.frames = state.done + 1, first
        if progress is not None:
            progress(state)
    if writer is None:
        raise ConflictError(f"{queries.ref(name, version)} has no episodes to export")
    return writer.finish(records)


def _episode_series(sources: Sources, episode: DatasetEpisode, spec: ExportSpec) -> dict[str, Series]:
    opened = open_run(sources, RunRef(episode.run_id, episode.robot_id, ""))
    if isinstance(opened, Skipped):
        raise ConflictError(f"episode {episode.episode} (run {episode.run_id}): {opened.why}")
    try:
        wanted = set(queries.chunk_ids_of(episode))
        rows = [r for r in opened.index() if r.chunk_id in wanted and r.entity_path is not None]
        kinds = {t.type for r in rows for t in r.timelines if t.name == episode.timeline}
        if kinds - set(TIME_TYPES):
            raise BadParameterError(
                "timeline",
                f"{episode.timeline} is a {', '.join(sorted(kinds))} timeline: frames per second need a timestamp "
                "or duration timeline (make the snapshot with --timeline log_time, say)",
            )
        paths = {r.entity_path for r in rows if r.entity_path is not None}
        entities = {
            p for p in paths if matches(spec.observation, p) or matches(spec.action, p) or p in dict(spec.cameras)
        }
        return read_series(_chunks(opened, [r for r in rows if r.entity_path in entities]), episode.timeline, entities)
    finally:
        opened.close()


def _chunks(opened: Any, rows: list[Any]) -> Iterator[tuple[ArrowMessage, ChunkMeta]]:
    for event in read_events(opened, rows):
        if isinstance(event, ArrowMessage):
            yield event, chunk_meta(event)


def _features(series: dict[str, Series], spec: ExportSpec) -> Features:
    """The features, from the first episode's data: each vector's entities and their widths."""
    vectors = [
        Vector(key, tuple(_names(series, patterns)))
        for key, patterns in (("observation.state", spec.observation), ("action", spec.action))
        if patterns
    ]
    cameras = []
    for entity, key in spec.cameras:
        found = series.get(entity)
        if found is None or not found.values:
            raise ConflictError(f"camera {entity}: no image in the first episode")
        height, width, _ = found.values[0].rgb().shape
        cameras.append(Camera(key, height, width, spec.codec))
    return Features(vectors, cameras)


def _names(series: dict[str, Series], patterns: Sequence[str]) -> list[str]:
    names: list[str] = []
    for entity in sorted(e for e in series if matches(patterns, e)):
        width = len(series[entity].values[0]) if series[entity].values else 0
        names += [entity] if width == 1 else [f"{entity}[{i}]" for i in range(width)]
    if not names:
        raise ConflictError(f"no scalars of {', '.join(patterns)} in the first episode")
    return names


def _on_grid(episode: DatasetEpisode, series: dict[str, Series], spec: ExportSpec, features: Features) -> Episode:
    """The episode's frames: latest-at values at each time of its grid."""
    sources = [s for s in series.values() if len(s.times)]
    if not sources:
        raise ConflictError(f"episode {episode.episode} (run {episode.run_id}) holds none of the exported entities")
    start = episode.range_start if episode.range_start is not None else min(int(s.times[0]) for s in sources)
    end = episode.range_end if episode.range_end is not None else max(int(s.times[-1]) for s in sources)
    grid = np.arange(start, end + 1, NS // spec.fps, dtype=np.int64)
    taken = {entity: s.at(grid) for entity, s in series.items()}
    first_full = max((int(np.argmax(i >= 0)) if (i >= 0).any() else len(grid)) for i in taken.values())
    grid = grid[first_full:]
    vectors: dict[str, np.ndarray] = {}
    for vector in features.vectors:
        patterns = spec.observation if vector.key == "observation.state" else spec.action
        columns = []
        for entity in sorted(e for e in series if matches(patterns, e)):
            at = taken[entity][first_full:]
            columns.append(np.stack([series[entity].values[i] for i in at]))
        values = np.concatenate(columns, axis=1).astype(np.float32) if columns else np.zeros((len(grid), 0))
        if values.shape[1] != len(vector.names):
            raise ConflictError(
                f"episode {episode.episode} (run {episode.run_id}): {vector.key} has {values.shape[1]} values, "
                f"the dataset's first episode {len(vector.names)}"
            )
        vectors[vector.key] = values
    cameras = {key: _frames(series[entity], taken[entity][first_full:]) for entity, key in spec.cameras}
    return Episode(episode.episode, spec.task, len(grid), vectors, cameras)


def _frames(found: Series, at: np.ndarray) -> Iterator[np.ndarray]:
    """The camera's frame at each grid time (an image decoded once however many frames repeat it)."""
    last, rgb = -1, None
    for index in at:
        if index != last:
            rgb, last = found.values[int(index)].rgb(), int(index)
        assert rgb is not None
        yield rgb
