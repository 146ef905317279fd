"""An episode's frames: its grid and the entities each feature takes (`plan`), the features from the
first exported episode (`features`), the state and action vectors at each grid time (`vectors`),
and each camera's frames decoded one at a time as its video is written (`frames`). Problems found
on the way are flagged on the episode's `EpisodeQuality`.

A row without a value is skipped; a frame before an entity's first value (its first rows had
none) takes that first value.
"""

from __future__ import annotations

import functools
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from core.errors import BadParameterError, ConflictError
from services.datasets import grid as sampling
from services.datasets import quality as checks
from services.datasets.lerobot.layout import Camera, Features, Vector
from services.datasets.quality import EpisodeQuality, Flag
from services.datasets.samples import SampleError, read_series
from services.rrd.chunk_index import IndexRow
from services.runs.download import EntityFilter
from services.runs.indexed import IndexedRecording

TIME_TYPES = ("timestamp", "duration")
CAMERA_SLICE_FRAMES = 32
STATE, ACTION = "observation.state", "action"


class Wanted(Protocol):
    """What an export takes (`ExportSpec`)."""

    @property
    def observation(self) -> tuple[str, ...]: ...
    @property
    def action(self) -> tuple[str, ...]: ...
    @property
    def cameras(self) -> tuple[tuple[str, str], ...]: ...
    @property
    def fps(self) -> int: ...


def matches(patterns: Sequence[str], path: str) -> bool:
    return bool(patterns) and _filter(tuple(patterns))(path)


@functools.lru_cache(maxsize=64)
def _filter(patterns: tuple[str, ...]) -> EntityFilter:
    return EntityFilter(list(patterns))


@dataclass
class EpisodePlan:
    timeline: str
    grid: np.ndarray
    vector_entities: dict[str, list[str]]  # feature key -> its entities, sorted
    rows: dict[str, list[IndexRow]]  # entity -> its timed chunk rows, by first time
    recording: IndexedRecording


def plan(
    timeline: str,
    window: tuple[int | None, int | None],
    recording: IndexedRecording,
    rows: Sequence[IndexRow],
    spec: Wanted,
    quality: EpisodeQuality,
) -> EpisodePlan | None:
    """The episode's grid and the entities each feature takes; None (flagged): nothing to export."""
    kinds = {t.type for r in rows for t in r.timelines if t.name == timeline}
    if kinds - set(TIME_TYPES):
        raise BadParameterError(
            "timeline",
            f"{timeline} is a {', '.join(sorted(kinds))} timeline: frames per second need a timestamp "
            "or duration timeline (make the snapshot with --timeline log_time, say)",
        )
    cameras = dict(spec.cameras)
    timed = sampling.timed_rows(
        rows, timeline, lambda p: matches(spec.observation, p) or matches(spec.action, p) or p in cameras
    )
    by_entity: dict[str, list[IndexRow]] = {}
    for row in timed:
        assert row.entity_path is not None
        by_entity.setdefault(row.entity_path, []).append(row)
    vector_entities: dict[str, list[str]] = {}
    for key, patterns in ((STATE, spec.observation), (ACTION, spec.action)):
        if not patterns:
            continue
        vector_entities[key] = sorted(e for e in by_entity if matches(patterns, e))
        for pattern in patterns:
            if not any(matches([pattern], e) for e in by_entity):
                quality.add(Flag(checks.MISSING, pattern, f"no rows of {pattern} on {timeline} ({key})"))
    for entity, key in spec.cameras:
        if entity not in by_entity:
            quality.add(Flag(checks.MISSING, entity, f"no image of {entity} on {timeline} ({key})"))
    if not by_entity or quality.blocked():
        return None
    firsts = sampling.first_times(timed, timeline)
    start = window[0] if window[0] is not None else min(firsts.values())
    end = window[1] if window[1] is not None else (sampling.last_time(timed, timeline) or start)
    times = sampling.grid_times(start, end, spec.fps)
    times = times[times >= max(firsts.values())]
    if not len(times):
        quality.add(Flag(checks.EMPTY, None, "no frame: the window ends before every exported entity has a row"))
        return None
    return EpisodePlan(timeline, times, vector_entities, by_entity, recording)


def features(episode: EpisodePlan, spec: Wanted, codec: str) -> Features:
    """The features, from the first exported episode: each vector's entities and widths (from each
    entity's first value), each camera's frame size (from its first image)."""
    vectors = []
    for key, entities in episode.vector_entities.items():
        names: list[str] = []
        for entity in entities:
            width = len(_first_value(episode, entity))
            names += [entity] if width == 1 else [f"{entity}[{i}]" for i in range(width)]
        vectors.append(Vector(key, tuple(names)))
    cameras = []
    for entity, key in spec.cameras:
        height, width, _ = _image(_first_value(episode, entity), entity).shape
        cameras.append(Camera(key, height, width, codec))
    return Features(vectors, cameras)


def _first_value(episode: EpisodePlan, entity: str) -> Any:
    read = sampling.reader(episode.recording)
    for row in episode.rows[entity]:  # by first time: the first chunk with a value holds the first value
        found = read_series(read([row]), episode.timeline, {entity}).get(entity)
        if found is not None and found.values:
            return found.values[0]
    raise ConflictError(f"{entity}: no value in the first exported episode")


def vectors(episode: EpisodePlan, first: Features | None, quality: EpisodeQuality) -> dict[str, np.ndarray] | None:
    """Each vector feature's values at the grid times (float32, frames x names); None (flagged):
    this episode's entities do not fill the features of the first exported one."""
    entities = sorted({e for found in episode.vector_entities.values() for e in found})
    rows = sorted(
        (r for e in entities for r in episode.rows[e]), key=lambda r: (sampling.span(r, episode.timeline) or (0, 0))[0]
    )
    sampler = sampling.GridSampler(rows, episode.timeline, sampling.reader(episode.recording), quality)
    taken: dict[str, list[Any]] = {e: [] for e in entities}
    for part in sampler.slices(episode.grid):
        for entity in entities:
            values = part.values[entity]
            taken[entity] += [values[i] if i >= 0 else None for i in part.picks[entity].tolist()]
    columns: dict[str, np.ndarray] = {}
    for entity, found in taken.items():
        filled = _filled(found)
        if filled is None or len({len(v) for v in filled}) != 1:
            quality.add(Flag(checks.SHAPE, entity, "its rows hold different numbers of values"))
            return None
        columns[entity] = np.stack(filled)
    widths = {v.key: len(v.names) for v in first.vectors} if first is not None else {}
    out: dict[str, np.ndarray] = {}
    for key, found in episode.vector_entities.items():
        joined = np.concatenate([columns[e] for e in found], axis=1).astype(np.float32)
        if key in widths and joined.shape[1] != widths[key]:
            said = f"{key} has {joined.shape[1]} values ({', '.join(found)}); the first exported episode {widths[key]}"
            quality.add(Flag(checks.SHAPE, None, said))
            return None
        out[key] = joined
    return out


def _filled(values: list[Any]) -> list[Any] | None:
    """Frames before the entity's first value take that value; None: it has none."""
    first = next((v for v in values if v is not None), None)
    if first is None:
        return None
    return [first if v is None else v for v in values]


def camera_slices(episode: EpisodePlan, entity: str, quality: EpisodeQuality) -> Iterator[sampling.SampledSlice]:
    """The camera's rows on the grid, in slices of CAMERA_SLICE_FRAMES: an image is large, so a slice
    holds about a second of them."""
    read = sampling.reader(episode.recording)
    sampler = sampling.GridSampler(episode.rows[entity], episode.timeline, read, quality)
    return sampler.slices(episode.grid, CAMERA_SLICE_FRAMES)


def frames(episode: EpisodePlan, entity: str, camera: Camera, quality: EpisodeQuality) -> Iterator[np.ndarray]:
    """The camera's frame at each grid time, decoded when its row changes (frames before its first
    image take that image)."""
    waiting = 0
    last_value: Any = None
    rgb: np.ndarray | None = None
    for part in camera_slices(episode, entity, quality):
        values = part.values[entity]
        for index in part.picks[entity].tolist():
            if index < 0:
                waiting += 1
                continue
            value = values[index]
            if value is not last_value:
                rgb, last_value = _image(value, entity), value
                if rgb.shape[:2] != (camera.height, camera.width):
                    raise ConflictError(
                        f"camera {entity}: a {rgb.shape[1]}x{rgb.shape[0]} image; the export's first episode's are "
                        f"{camera.width}x{camera.height} (export such episodes separately)"
                    )
            assert rgb is not None
            for _ in range(waiting + 1):
                yield rgb
            waiting = 0


def _image(value: Any, entity: str) -> np.ndarray:
    try:
        rgb: np.ndarray = value.rgb()
    except (SampleError, AttributeError) as exc:
        raise ConflictError(f"camera {entity}: {exc}") from exc
    return rgb
