"""Choosing the chunks of a time window, and the rows that make the scene at its start complete.

Rerun's latest-at at `start` shows, per entity and component, the newest row (by time, ties by row
id) before `start` where that component is not null, or a row inside the window. A download keeps,
for each (entity, component), the chunk(s) that may hold that newest earlier row:

- chunks whose component range ends before `start`, those with the newest end (ties included, as a
  tie is settled by row id), unless a chunk straddling `start` has a later earlier row for sure;
- chunks whose component range straddles `start` (their earlier rows are only known by reading).

With `exact=true` those candidates are read, the true newest earlier row of each component is found,
and every chunk is cut to the rows in the window plus the rows picked here.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from services.rrd.chunk import ChunkMeta, read_chunk
from services.rrd.messages import ArrowMessage
from services.sealed.index import IndexTable, flags, one_array


@dataclass(frozen=True)
class ChunkEntry:
    """What choosing chunks for a time window needs to know of one chunk (from its metadata, or
    from a sealed run's chunk index without reading the chunk)."""

    chunk_id: bytes
    entity_path: str
    is_static: bool
    is_recording: bool
    span: tuple[int, int] | None  # on the window's timeline; None: not on it
    # component -> (min, max) of its non-null rows on that timeline; None: not known (an index written
    # before it kept per-component ranges), the chunk is read when it matters
    component_spans: dict[str, tuple[int, int]] | None
    components: tuple[str, ...] = ()  # the chunk's components (what `component_spans` would cover)

    @classmethod
    def of_meta(cls, meta: ChunkMeta, is_recording: bool, timeline: str) -> ChunkEntry:
        span = next(((t.range.min, t.range.max) for t in meta.timelines if t.name == timeline), None)
        comps = {
            c.component: (c.ranges[timeline].min, c.ranges[timeline].max)
            for c in meta.components
            if timeline in c.ranges
        }
        return cls(
            meta.chunk_id,
            meta.entity_path,
            meta.is_static,
            is_recording,
            span,
            comps,
            tuple(c.component for c in meta.components),
        )


# Reads chunks whose component ranges are not known and returns them with their ranges.
Resolve = Callable[[list[ChunkEntry]], list[ChunkEntry]]


def select_chunks(
    entries: list[ChunkEntry], bounds: tuple[int, int], latest_at: bool, resolve: Resolve
) -> tuple[set[bytes], set[bytes]]:
    """Chunk ids to keep (static ones, those overlapping [lo, hi], the latest-at candidates), and the
    latest-at candidates apart (the chunks an exact download reads to find each newest earlier row)."""
    lo, hi = bounds
    keep: set[bytes] = set()
    earlier: list[ChunkEntry] = []  # chunks with rows before start
    for entry in entries:
        if not entry.is_recording or entry.is_static:
            keep.add(entry.chunk_id)
        elif entry.span is not None:  # else: not on the chosen timeline
            if entry.span[1] >= lo and entry.span[0] <= hi:
                keep.add(entry.chunk_id)  # overlaps the window (by its index column)
            if latest_at and entry.span[0] < lo:
                earlier.append(entry)
    candidates = _candidates(_known(earlier, lo, resolve), lo)
    return keep | candidates, candidates


def _candidates(entries: list[ChunkEntry], lo: int) -> set[bytes]:
    groups: dict[tuple[str, str], list[tuple[bytes, int, int]]] = defaultdict(list)
    for entry in entries:
        for component, (first, last) in (entry.component_spans or {}).items():
            if first < lo:
                groups[(entry.entity_path, component)].append((entry.chunk_id, first, last))
    out: set[bytes] = set()
    for members in groups.values():
        before_end = max((last for _, _, last in members if last < lo), default=None)
        # a straddling chunk has an earlier row at its component start at least: a later one than every
        # chunk entirely before start wins for sure, an equal one may tie (row ids settle it)
        straddle_start = max((first for _, first, last in members if last >= lo), default=None)
        for chunk_id, _, last in members:
            if last >= lo or (last == before_end and (straddle_start is None or straddle_start <= last)):
                out.add(chunk_id)
    return out


_MAY_KEEP_READS = ("store_kind", "is_static", "timelines", "component_ranges", "entity_path")  # of the index


def may_keep(
    index: IndexTable, positions: list[int], timeline: str, bounds: tuple[int, int], latest_at: bool
) -> Any | None:
    """`select_chunks` from a sealed index's columns, without making their rows: which of the chunks
    at `positions` it may keep, a boolean numpy array (one per position). Those it keeps for sure
    (blueprint and static ones, those overlapping the window), and with `latest_at` per entity and
    component the chunks reaching the start and those ending last before it, as `_candidates` has
    them. Of these alone `select_chunks` keeps what it keeps of all (the newest end and every
    straddling member of each group are among them), so a window of a long run makes the rows of a
    few chunks, not of all its entity's. None where the columns cannot tell: an index from before
    per-component ranges (`_known` then reads chunks)."""
    chunks = index.columns(positions, _MAY_KEEP_READS)  # only what is read here is taken
    lo, hi = bounds
    always = ~flags(pc.equal(chunks.column("store_kind"), "recording")) | flags(chunks.column("is_static"))
    span_min, span_max, on_timeline = _spans(one_array(chunks.column("timelines")), timeline, chunks.num_rows)
    keep = always | (on_timeline & (span_max >= lo) & (span_min <= hi))
    earlier = np.flatnonzero(on_timeline & (span_min < lo) & ~always)
    if latest_at and len(earlier):
        ranges = one_array(chunks.column("component_ranges")).take(pa.array(earlier, pa.int64()))
        if ranges.null_count:
            return None
        newest = _newest_before(ranges, one_array(chunks.column("entity_path")).take(earlier), timeline, lo)
        keep[earlier[newest]] = True
    return keep


def _spans(timelines: pa.ListArray, timeline: str, count: int) -> tuple[Any, Any, Any]:
    """Each row's min and max on `timeline`, and whether it is on it (numpy arrays of `count`)."""
    flat, parents = timelines.flatten(), pc.list_parent_indices(timelines).to_numpy()
    on = flags(pc.equal(flat.field("name"), timeline))
    span_min, span_max = np.zeros(count, np.int64), np.zeros(count, np.int64)
    on_timeline = np.zeros(count, bool)
    span_min[parents[on]] = _ints(flat.field("min"))[on]
    span_max[parents[on]] = _ints(flat.field("max"))[on]
    on_timeline[parents[on]] = True
    return span_min, span_max, on_timeline


def _newest_before(ranges: pa.ListArray, entities: pa.Array, timeline: str, lo: int) -> Any:
    """`_candidates` over columns: which of the rows whose `ranges` (component ranges) are given hold,
    for some (entity, component) on `timeline`, a range starting before `lo` that reaches it or ends
    last before it: a boolean numpy array, one per row."""
    flat, parents = ranges.flatten(), pc.list_parent_indices(ranges).to_numpy()
    first = _ints(flat.field("min"))
    last = _ints(flat.field("max"))
    member = flags(pc.equal(flat.field("timeline"), timeline)) & (first < lo)
    entity_codes = pc.dictionary_encode(pc.fill_null(entities, "")).indices.to_numpy()[parents]
    component_codes = pc.dictionary_encode(flat.field("component")).indices.to_numpy().astype(np.int64)
    _, group = np.unique(
        entity_codes.astype(np.int64) * (component_codes.max(initial=0) + 1) + component_codes, return_inverse=True
    )
    before = member & (last < lo)
    newest_end = np.full(group.max(initial=0) + 1, np.iinfo(np.int64).min)
    np.maximum.at(newest_end, group[before], last[before])
    wanted = member & ((last >= lo) | (before & (last == newest_end[group])))
    out = np.zeros(len(ranges), bool)
    out[parents[wanted]] = True
    return out


def _ints(values: pa.Array) -> Any:
    """An int64 column as a numpy array (null, which the index never writes for a range: 0)."""
    return pc.fill_null(values, 0).to_numpy(zero_copy_only=False)


def _known(entries: list[ChunkEntry], lo: int, resolve: Resolve) -> list[ChunkEntry]:
    """`entries` with their component ranges, reading only the chunks that may matter: those that
    reach `start`, and per entity those entirely before it from the newest back, until every
    component's newest end is found and the next chunk ends before it."""
    known = [e for e in entries if e.component_spans is not None]
    unknown = [e for e in entries if e.component_spans is None]
    if not unknown:
        return known
    known += resolve([e for e in unknown if e.span is not None and e.span[1] >= lo])
    by_entity: dict[str, list[ChunkEntry]] = defaultdict(list)
    for entry in unknown:
        if entry.span is not None and entry.span[1] < lo:
            by_entity[entry.entity_path].append(entry)
    for chunks in by_entity.values():
        chunks.sort(key=lambda e: e.span[1] if e.span else 0, reverse=True)
        names = {c for e in chunks for c in e.components}
        newest: dict[str, int] = {}
        for entry in chunks:
            assert entry.span is not None
            if all(newest.get(c, entry.span[1]) > entry.span[1] for c in names):
                break  # every component has a newer row than anything this chunk (or an older one) holds
            (resolved,) = resolve([entry])
            known.append(resolved)
            for component, (_, last) in (resolved.component_spans or {}).items():
                newest[component] = max(newest.get(component, last), last)
    return known


def pick_rows(messages: Iterable[tuple[ArrowMessage, ChunkMeta]], timeline: str, lo: int) -> dict[bytes, set[int]]:
    """Per chunk id, the rows (positions) holding some component's newest value before `lo`, found
    among `messages` (the latest-at candidates): by time, ties by row id, over all of them."""
    best: dict[tuple[str, str], tuple[int, Any, bytes, int]] = {}
    for msg, meta in messages:
        index = next((ix for ix in meta.layout.indexes if ix.name == timeline), None)
        if index is None:
            continue
        batch = read_chunk(msg)
        column = batch.column(index.position)
        times = pc.fill_null(column.view(pa.int64()) if column.type != pa.int64() else column, 0).to_numpy()
        before = column.is_valid().to_numpy(zero_copy_only=False) & (times < lo)
        if not before.any():
            continue
        row_ids = _row_ids(batch, meta)
        for col in meta.layout.data:
            rows = np.flatnonzero(before & batch.column(col.position).is_valid().to_numpy(zero_copy_only=False))
            if not len(rows):
                continue
            newest = int(times[rows].max())
            row = max((int(r) for r in rows if times[r] == newest), key=lambda r: row_ids[r])
            key, found = (meta.entity_path, col.component), (newest, row_ids[row], meta.chunk_id, row)
            if key not in best or found[:2] > best[key][:2]:
                best[key] = found
    picks: dict[bytes, set[int]] = defaultdict(set)
    for _, _, chunk_id, row in best.values():
        picks[chunk_id].add(row)
    return dict(picks)


def _row_ids(batch: pa.RecordBatch, meta: ChunkMeta) -> list[Any]:
    """Comparable row ids: TUID bytes (big-endian time, then increment) or their struct form as a tuple."""
    if meta.row_id_field is None:
        return [0] * batch.num_rows
    values = batch.column(batch.schema.get_field_index(meta.row_id_field.name)).to_pylist()
    return [tuple(v.values()) if isinstance(v, dict) else (v if v is not None else b"") for v in values]
