"""Which chunks of a run a query may need, from its chunk index alone (no chunk is read).

The answer may hold more chunks than needed (Rerun's protocol allows it: the client resolves the
rows), never fewer. Pushed down: the entities and components asked for (a chunk holding none of the
components is left out), static chunks only, a time range on one timeline (bounds inclusive), the
sample times of a resampling, and latest-at fill: per entity and component, the chunks that may
hold its newest value before the range start or a sample time (`services.runs.latest_at`, from the
per-component ranges the index keeps).
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from services.runs.latest_at import ChunkEntry, select_chunks
from services.sealed.index import IndexRow

# Above this many sample times, latest-at fill is found once, at the first of them, and every chunk
# between the first and the last is kept: a superset found in one pass, not one pass a sample.
EXACT_SAMPLES = 32
_LOWEST, _HIGHEST = -(2**63), 2**63 - 1


@dataclass(frozen=True)
class Contents:
    """The entities asked for, each with its components (None: all of them); `entities` None: all."""

    entities: Mapping[str, frozenset[str] | None] | None = None

    def components(self, row: IndexRow) -> frozenset[str] | None:
        """The row's components asked for (None: all), or an empty set when none is."""
        if self.entities is None:
            return None
        wanted = self.entities.get(normal_entity_path(row.entity_path or ""), frozenset())
        return None if wanted is None else wanted & frozenset(row.components)

    def admits(self, row: IndexRow) -> bool:
        wanted = self.components(row)
        return wanted is None or bool(wanted)


@dataclass(frozen=True)
class StaticOnly:
    """The static chunks."""


@dataclass(frozen=True)
class Everything:
    """Every chunk: a query that narrows nothing in time."""


@dataclass(frozen=True)
class TimeRange:
    """Chunks with data in [start, end] on `timeline` (None: unbounded), static ones, and with
    `latest_at` those that may hold the newest value before `start`."""

    timeline: str
    start: int | None = None
    end: int | None = None
    latest_at: bool = False


@dataclass(frozen=True)
class Samples:
    """Chunks with data at the given times on `timeline`, static ones, and with `latest_at` those
    that may hold the newest value before each time."""

    timeline: str
    times: tuple[int, ...]
    latest_at: bool = False


Mode = StaticOnly | Everything | TimeRange | Samples


def normal_entity_path(path: str) -> str:
    """`world/points`, `/world/points/` and `/world/points` name one entity."""
    return "/" + "/".join(p for p in path.split("/") if p)


def span(row: IndexRow, timeline: str) -> tuple[int, int] | None:
    return next(((t.min, t.max) for t in row.timelines if t.name == timeline), None)


def select(rows: Sequence[IndexRow], contents: Contents, mode: Mode) -> list[IndexRow]:
    """The rows of the chunks the query may need, in index order."""
    admitted = [r for r in rows if contents.admits(r)]
    if isinstance(mode, StaticOnly):
        return [r for r in admitted if r.is_static]
    if isinstance(mode, Everything) or (isinstance(mode, TimeRange) and mode.start is None and mode.end is None):
        return admitted  # no bound: every chunk, on the timeline or not (as Rerun answers)
    if isinstance(mode, TimeRange):
        lo = _LOWEST if mode.start is None else mode.start
        hi = _HIGHEST if mode.end is None else mode.end
        chosen = _overlapping(admitted, mode.timeline, lo, hi)
        if mode.latest_at:
            chosen |= _latest_at(admitted, contents, mode.timeline, lo)
        return _in_order(admitted, chosen)
    if not mode.times:
        return []  # a segment without sample times selects nothing, not even its static chunks
    times = sorted(set(mode.times))
    if len(times) > EXACT_SAMPLES:
        chosen = _overlapping(admitted, mode.timeline, times[0], times[-1])
        fill_at: Iterable[int] = times[:1]
    else:
        chosen = _at_times(admitted, mode.timeline, times)
        fill_at = times
    if mode.latest_at:
        for time in fill_at:
            chosen |= _latest_at(admitted, contents, mode.timeline, time)
    return _in_order(admitted, chosen)


def _in_order(rows: Sequence[IndexRow], chosen: set[int]) -> list[IndexRow]:
    return [r for r in rows if id(r) in chosen]


def _overlapping(rows: Sequence[IndexRow], timeline: str, lo: int, hi: int) -> set[int]:
    """Static rows and rows with data on `timeline` overlapping [lo, hi] (ids of the rows)."""
    out = set()
    for row in rows:
        found = span(row, timeline)
        if row.is_static or (found is not None and found[1] >= lo and found[0] <= hi):
            out.add(id(row))
    return out


def _at_times(rows: Sequence[IndexRow], timeline: str, times: list[int]) -> set[int]:
    """Static rows and rows whose span on `timeline` holds one of `times` (sorted)."""
    out = set()
    for row in rows:
        found = span(row, timeline)
        if row.is_static:
            out.add(id(row))
        elif found is not None:
            at = bisect.bisect_left(times, found[0])
            if at < len(times) and times[at] <= found[1]:
                out.add(id(row))
    return out


def _latest_at(rows: Sequence[IndexRow], contents: Contents, timeline: str, lo: int) -> set[int]:
    """Rows of chunks that may hold, per entity and component asked for, the newest value before
    `lo`. Chunks whose per-component ranges an older index did not keep are all taken when they
    start before `lo`; the others are chosen by their ranges."""
    by_id: dict[bytes, IndexRow] = {}
    entries: list[ChunkEntry] = []
    out: set[int] = set()
    for row in rows:
        found = span(row, timeline)
        if row.is_static or found is None or found[0] >= lo:
            continue
        if row.component_ranges is None:
            out.add(id(row))
            continue
        wanted = contents.components(row)
        spans = {
            c.component: (c.min, c.max)
            for c in row.component_ranges
            if c.timeline == timeline and (wanted is None or c.component in wanted)
        }
        key = row.chunk_id or str(id(row)).encode()
        by_id[key] = row
        entries.append(ChunkEntry(key, row.entity_path or "", False, True, found, spans, tuple(spans)))
    _, candidates = select_chunks(entries, (lo, lo), True, _nothing_to_resolve)
    out.update(id(by_id[chunk_id]) for chunk_id in candidates)
    return out


def _nothing_to_resolve(entries: list[ChunkEntry]) -> list[ChunkEntry]:
    raise AssertionError("every entry given to select_chunks has its component ranges")
