"""An episode's entities sampled onto a grid of times by latest-at, in slices, so memory stays
bounded whatever the episode's length: only the chunks that hold rows up to the slice's last time
are read, and each entity's rows are dropped once a later row of it is known at or before that
time.

Chunks are read in the order of their first time on the timeline. When a slice ends at time T,
every chunk whose first time is at most T has been read, so every row at or before T is known:
the latest-at value at each grid time of the slice is exact, however the chunks' rows interleave
(a chunk's rows out of order, chunks that overlap). What an entity keeps between slices is its
latest row so far and the rows read ahead of T.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.datasets.quality import EpisodeQuality
from services.datasets.samples import Series, read_series
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.chunk_index import CHUNK, IndexRow
from services.rrd.messages import ArrowMessage
from services.runs.indexed import IndexedRecording, read_events

NS = 1_000_000_000
SLICE_FRAMES = 256  # grid times sampled per slice
ReadRows = Callable[[list[IndexRow]], Iterator[tuple[ArrowMessage, ChunkMeta]]]


def span(row: IndexRow, timeline: str) -> tuple[int, int] | None:
    """The chunk's (min, max) on the timeline; None: it has no row on it (static, or another timeline)."""
    for t in row.timelines:
        if t.name == timeline:
            return t.min, t.max
    return None


def timed_rows(rows: Sequence[IndexRow], timeline: str, wanted: Callable[[str], bool]) -> list[IndexRow]:
    """The recording chunks of wanted entities that have rows on the timeline, by their first time."""
    found = [
        r
        for r in rows
        if r.kind == CHUNK
        and r.store_kind == "recording"
        and r.entity_path is not None
        and wanted(r.entity_path)
        and not r.is_static
        and span(r, timeline) is not None
    ]
    return sorted(found, key=lambda r: (span(r, timeline) or (0, 0))[0])


def grid_times(start: int, end: int, fps: int) -> np.ndarray:
    """Times from `start` to `end` (inclusive) every 1/fps s, in nanoseconds."""
    step = NS // fps
    return np.arange(start, end + 1, step, dtype=np.int64) if end >= start else np.zeros(0, dtype=np.int64)


def reader(recording: IndexedRecording) -> ReadRows:
    """Ranged reads of the given rows of `recording`: their chunks, decoded."""

    def read(rows: list[IndexRow]) -> Iterator[tuple[ArrowMessage, ChunkMeta]]:
        ordered = sorted(rows, key=lambda r: r.offset)
        for event in read_events(recording, ordered):
            if isinstance(event, ArrowMessage):
                yield event, chunk_meta(event)

    return read


@dataclass
class Seen:
    """What an entity holds between slices: its rows not yet behind the slice's end, in time order."""

    series: Series = field(default_factory=Series)


@dataclass
class SampledSlice:
    """Grid times of one slice and, per entity, the index into `values` of the latest row at or
    before each (-1: none yet), with the rows those indexes point at."""

    grid: np.ndarray
    picks: dict[str, np.ndarray]
    values: dict[str, list[Any]]


class GridSampler:
    """Latest-at samples of `rows`' entities on `timeline`, slice by slice of `grid`.

    `quality` (optional) sees each entity's rows as read, and the rows at a time another row of
    the entity already has."""

    def __init__(
        self, rows: Sequence[IndexRow], timeline: str, read: ReadRows, quality: EpisodeQuality | None = None
    ) -> None:
        self.rows = list(rows)  # sorted by first time (`timed_rows`)
        self.timeline, self.read, self.quality = timeline, read, quality
        self.entities = sorted({r.entity_path for r in self.rows if r.entity_path is not None})
        self._next = 0
        self._seen: dict[str, Seen] = {e: Seen() for e in self.entities}

    def slices(self, grid: np.ndarray, frames: int = SLICE_FRAMES) -> Iterator[SampledSlice]:
        for first in range(0, len(grid), frames):
            part = grid[first : first + frames]
            yield self._sample(part)

    def _sample(self, part: np.ndarray) -> SampledSlice:
        until = int(part[-1])
        due: list[IndexRow] = []
        while self._next < len(self.rows) and (span(self.rows[self._next], self.timeline) or (0, 0))[0] <= until:
            due.append(self.rows[self._next])
            self._next += 1
        if due:
            wanted = {r.entity_path for r in due if r.entity_path is not None}
            observe = self.quality.rows if self.quality is not None else None
            for entity, found in read_series(self.read(due), self.timeline, wanted, observe).items():
                held = self._seen[entity].series
                times = np.concatenate([held.times, found.times])
                rows = held.values + found.values
                order = np.argsort(times, kind="stable")
                merged = Series(times[order], [rows[i] for i in order])
                if self.quality is not None:  # repeats the rows just read brought
                    self.quality.duplicates(entity, _repeats(merged.times) - _repeats(held.times))
                self._seen[entity].series = merged
        picks: dict[str, np.ndarray] = {}
        values: dict[str, list[Any]] = {}
        for entity, seen in self._seen.items():
            series = seen.series
            at = series.at(part)
            picks[entity], values[entity] = at, series.values
            # keep the latest row at or before the slice's end, and every row after it
            keep_from = max(int(np.searchsorted(series.times, until, side="right")) - 1, 0)
            seen.series = Series(series.times[keep_from:], series.values[keep_from:])
        return SampledSlice(part, picks, values)


def _repeats(times: np.ndarray) -> int:
    return int(np.count_nonzero(np.diff(times) == 0)) if len(times) > 1 else 0


def first_times(rows: Sequence[IndexRow], timeline: str) -> dict[str, int]:
    """Each entity's first time on the timeline, from the index (no chunk read)."""
    out: dict[str, int] = {}
    for r in rows:
        bounds = span(r, timeline)
        if r.entity_path is not None and bounds is not None:
            out[r.entity_path] = min(out.get(r.entity_path, bounds[0]), bounds[0])
    return out


def last_time(rows: Sequence[IndexRow], timeline: str) -> int | None:
    ends = [b[1] for r in rows if (b := span(r, timeline)) is not None]
    return max(ends) if ends else None
