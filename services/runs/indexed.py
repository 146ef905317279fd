"""Serving a run from its chunk index: ranged reads planned from index rows, for either tier.

A run's chunk index (`chunks.parquet` beside a sealed recording, `chunks.idx` beside a hot run file)
says where every message of the recording lies, with its entity and time ranges. A download picks
the messages it keeps from the index alone and reads only those, neighbouring ones in one read, so a
one-entity download of a ten-entity run reads about a tenth of the recording. The messages kept are
copied as they are, and the footer's manifest is built from each chunk's metadata: a hot run's index
holds it, so nothing is decompressed; a sealed run's `chunks.parquet` does not (it lacks the chunks'
schemas), so its kept chunks are read for it. An exact window reads and cuts the chunks it trims.

An unfiltered hot download is thus the run file's first `size` bytes as they are, followed by the
End message and footer that make it a complete stream (a chunk from an SDK before 0.24, which sent
no chunk id, gets it appended, as in any download).
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from core.errors import UnavailableError
from services.hot.read import HotRecording
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.chunk_index import BLUEPRINT_ACTIVATION, CHUNK, STORE_INFO, IndexRow, IndexRows
from services.rrd.decoder import decode_message
from services.rrd.frames import MESSAGE_HEADER_SIZE, STREAM_HEADER_SIZE, decode_message_header, decode_stream_header
from services.rrd.messages import ArrowMessage, Event, StreamStart
from services.runs.download import FLUSH_BYTES, EntityFilter, TimeWindow, encode_run
from services.runs.latest_at import ChunkEntry, may_keep, pick_rows, select_chunks
from services.sealed.index import IndexTable
from services.storage import readahead
from services.storage.objectstore import ObjectStore

GAP_BYTES = 64 * 1024  # neighbouring messages closer than this are fetched in one read
MAX_READ_BYTES = 16 * 1024 * 1024  # one read holds at most this much (memory stays bounded)
# The first read is smaller, and each next one twice the last, up to the most: the first bytes go
# out soon, even when every row of a run's index has to be parsed before its message is read.
FIRST_READ_BYTES = 2 * FLUSH_BYTES

# (offset, length) -> those bytes of the recording
ReadRange = Callable[[int, int], bytes]


def _nothing() -> None:
    pass


@dataclass(frozen=True)
class IndexedRecording:
    """A run's recording opened for ranged reads planned from its chunk index, whichever tier holds
    it: a hot run's file up to the size its reader was given (`hot`), or a sealed run's object in
    the warm store (`store`, `key`). Downloads stream from it; the catalog server's manifests and
    FetchChunks read from it. `close()` it when done: a hot run's file is held open, so a run sealed
    meanwhile stays readable."""

    read: ReadRange
    size: int
    index: Callable[[], Iterable[IndexRow]]  # its rows in file order, read from the index when called
    # chunk metadata by frame offset, where the index holds it (a hot run's): what the footer's
    # manifest and the window's plan need, so those chunks are never decompressed
    metas: Mapping[int, ChunkMeta] = field(default_factory=dict)
    hot: HotRecording | None = None
    store: ObjectStore | None = None
    key: str = ""  # of the sealed recording in `store`
    close: Callable[[], None] = _nothing
    read_ahead: int = 1  # reads under way at once (a store's: each waits for its first byte)

    def chunk_row(self, chunk_id: bytes) -> IndexRow | None:
        """Where the chunk with this id is in the recording (None: not in it); the index is read
        once, on the first call."""
        return self._chunk_rows.get(chunk_id)

    @cached_property
    def _chunk_rows(self) -> dict[bytes, IndexRow]:
        return {r.chunk_id: r for r in self.index() if r.kind == CHUNK and r.chunk_id is not None}


def open_hot(hot: HotRecording) -> IndexedRecording:
    """A hot run's file as it stands (its first `hot.size` bytes), with its whole chunk index."""
    fd = os.open(hot.path, os.O_RDONLY)  # kept open: a run sealed meanwhile stays readable

    def read(offset: int, length: int) -> bytes:
        data = os.pread(fd, length, offset)
        if len(data) != length:  # a hot run file only grows: never shorter than its index says
            raise UnavailableError(f"hot run file {hot.path} is shorter than its index says: try again")
        return data

    return IndexedRecording(read, hot.size, lambda: hot.chunk_index().rows, hot=hot, close=lambda: os.close(fd))


def open_sealed_object(
    store: ObjectStore, key: str, size: int, index: Callable[[], Iterable[IndexRow]]
) -> IndexedRecording:
    """A sealed run's `recording.rrd` (`size` bytes) read by range from the warm store, with its
    chunk index as `index` reads it (nothing to close)."""

    def read(offset: int, length: int) -> bytes:
        return store.get_range(key, offset, length)

    return IndexedRecording(read, size, index, store=store, key=key, read_ahead=readahead.DEPTH)


def stream_indexed(
    recording: IndexedRecording, entities: EntityFilter, *, blueprint: bool = True, window: TimeWindow | None = None
) -> Iterator[bytes | memoryview]:
    """The messages a download keeps, read by range and copied as they are, as one RRD stream with
    a footer."""
    rows = recording.index()
    keep: set[bytes] | None = None
    picks: dict[bytes, set[int]] = {}
    if window is not None:  # planned over every chunk before the first is read
        plan = _PlanIndex.of(rows)
        keep, picks, positions = _plan_window(recording, plan, entities, window)
        rows = plan.candidates(positions, keep)
    yield from encode_run(
        read_events(recording, choose_rows(rows, entities, blueprint, keep)),
        entities,
        blueprint=blueprint,
        window=window,
        keep=keep,
        picks=picks,
        metas=recording.metas,
    )


def stream_hot(
    hot: HotRecording, entities: EntityFilter, *, blueprint: bool = True, window: TimeWindow | None = None
) -> Iterator[bytes | memoryview]:
    """A hot run as it stands (its file's first `hot.size` bytes), served from its chunk index."""
    recording = open_hot(hot)  # opened first: a run sealed meanwhile stays readable
    metas: dict[int, ChunkMeta] = {}
    try:
        if window is None:  # chosen in file order as the index is read: the first bytes go out at once
            rows: Iterable[IndexRow] = _checked(hot, _hot_rows(hot, metas))
        else:  # planned over every chunk's time ranges first
            index = hot.chunk_index()
            metas.update((e.offset, e.meta) for e in index.entries if e.meta is not None)
            rows = list(_checked(hot, index.rows))
        planned = replace(recording, index=lambda: rows, metas=metas)
        yield from stream_indexed(planned, entities, blueprint=blueprint, window=window)
    finally:
        recording.close()


def _hot_rows(hot: HotRecording, metas: dict[int, ChunkMeta]) -> Iterator[IndexRow]:
    """Where each message of a hot run lies and what it is, without its time ranges (what choosing
    by entity needs); each chunk's metadata is put in `metas` before its row is handed out."""
    for entry in hot.index_entries():
        meta = entry.meta
        if meta is None:
            yield IndexRow(entry.kind, entry.store_kind, entry.offset, entry.length)
            continue
        metas[entry.offset] = meta
        yield IndexRow(
            entry.kind, entry.store_kind, entry.offset, entry.length, meta.chunk_id, meta.entity_path, meta.is_static
        )


def _checked(hot: HotRecording, rows: Iterable[IndexRow]) -> Iterator[IndexRow]:
    """`rows`, then UNAVAILABLE unless they reach the size the reader was given (the run was sealed
    and its files removed while they were read)."""
    end = STREAM_HEADER_SIZE
    for row in rows:
        end = row.end
        yield row
    if end != hot.size:
        raise UnavailableError(f"run {hot.path.parent.name!r} was sealed while it was being read: try again")


@dataclass
class _PlanIndex:
    """A run's index rows arranged for planning windows: positions of the chunks of each entity, of
    the rows every download keeps, and each chunk's entry on a timeline once it was needed. Kept
    with a sealed run's cached index (`IndexRows.derived`), so a window of a run of many GB goes over
    the chunks of the entities it asks for, not over every row of the run."""

    rows: Sequence[IndexRow]
    by_entity: dict[str, list[int]]  # recording chunks
    blueprint_chunks: list[int]
    others: list[int]  # every row that is not a chunk (store infos, blueprint activations)
    entries: dict[str, dict[int, ChunkEntry]] = field(default_factory=dict)  # timeline -> position -> entry

    @classmethod
    def of(cls, rows: Iterable[IndexRow]) -> _PlanIndex:
        derived = rows.derived if isinstance(rows, IndexRows | IndexTable) else None
        found = derived.get("window_plan") if derived is not None else None
        if isinstance(found, _PlanIndex):
            return found
        if isinstance(rows, IndexTable):  # from its columns: rows are made only for the chunks chosen
            plan = cls(rows, *rows.groups())
        else:
            plan = cls._grouped(rows if isinstance(rows, Sequence) else list(rows))
        if derived is not None:
            derived["window_plan"] = plan
        return plan

    @classmethod
    def _grouped(cls, listed: Sequence[IndexRow]) -> _PlanIndex:
        by_entity: dict[str, list[int]] = {}
        blueprint_chunks, others = [], []
        for i, row in enumerate(listed):
            if row.kind != CHUNK:
                others.append(i)
            elif row.store_kind == "recording":
                by_entity.setdefault(row.entity_path or "", []).append(i)
            else:
                blueprint_chunks.append(i)
        return cls(listed, by_entity, blueprint_chunks, others)

    def at(self, positions: Iterable[int]) -> list[IndexRow]:
        """The rows at `positions` (an index read as columns makes them together)."""
        if isinstance(self.rows, IndexTable):
            return self.rows.at(positions)
        return [self.rows[i] for i in positions]

    def chunks(self, entities: EntityFilter) -> list[int]:
        """Positions of the chunks a window of these entities chooses from (blueprints' too), in order."""
        chosen = [i for entity, positions in self.by_entity.items() if entities(entity) for i in positions]
        return sorted(chosen + self.blueprint_chunks)

    def window_chunks(self, positions: list[int], window: TimeWindow) -> list[int]:
        """Of the chunks at `positions`, those `window` may keep, worked out from an index read as
        columns (`latest_at.may_keep`); all of them otherwise."""
        if isinstance(self.rows, IndexTable) and positions:
            kept = may_keep(self.rows, positions, window.timeline, window.bounds, window.latest_at)
            if kept is not None:
                return [positions[i] for i in np.flatnonzero(kept).tolist()]
        return positions

    def entries_on(self, timeline: str, positions: list[int]) -> list[ChunkEntry]:
        known = self.entries.setdefault(timeline, {})
        missing = [i for i in positions if i not in known]
        for i, row in zip(missing, self.at(missing), strict=True):
            known[i] = _entry(row, timeline)
        return [known[i] for i in positions]

    def candidates(self, chunks: list[int], keep: set[bytes]) -> list[IndexRow]:
        """The rows a download of the chunks in `keep` (of those at `chunks`) chooses from
        (`choose_rows`), in file order."""
        kept = [i for i, row in zip(chunks, self.at(chunks), strict=True) if row.chunk_id in keep]
        return self.at(sorted(self.others + kept))


def plan_window(
    recording: IndexedRecording, rows: Iterable[IndexRow], entities: EntityFilter, window: TimeWindow
) -> tuple[set[bytes], dict[bytes, set[int]]]:
    """The chunk ids a windowed download keeps, and for an exact one the latest-at rows of each chunk:
    only the candidate chunks are read (ranged reads), and with an index from before per-component
    ranges also the chunks whose ranges matter."""
    keep, picks, _ = _plan_window(recording, _PlanIndex.of(rows), entities, window)
    return keep, picks


def _plan_window(
    recording: IndexedRecording, plan: _PlanIndex, entities: EntityFilter, window: TimeWindow
) -> tuple[set[bytes], dict[bytes, set[int]], list[int]]:
    """`plan_window`, and the positions of the chunks it chose from."""
    positions = plan.window_chunks(plan.chunks(entities), window)
    chunks = plan.at(positions)

    def read(ids: set[bytes]) -> Iterator[tuple[ArrowMessage, ChunkMeta]]:
        for event in read_events(recording, [r for r in chunks if r.chunk_id in ids], header=False):
            if isinstance(event, ArrowMessage):
                yield event, recording.metas.get(event.offset) or chunk_meta(event)

    def resolve(entries: list[ChunkEntry]) -> list[ChunkEntry]:
        metas = {meta.chunk_id: meta for _, meta in read({e.chunk_id for e in entries})}
        return [ChunkEntry.of_meta(metas[e.chunk_id], True, window.timeline) for e in entries if e.chunk_id in metas]

    keep, candidates = select_chunks(
        plan.entries_on(window.timeline, positions), window.bounds, window.latest_at, resolve
    )
    picks = pick_rows(read(candidates), window.timeline, window.bounds[0]) if window.exact and candidates else {}
    return keep, picks, positions


def _entry(row: IndexRow, timeline: str) -> ChunkEntry:
    span = next(((t.min, t.max) for t in row.timelines if t.name == timeline), None)
    spans = (
        None
        if row.component_ranges is None
        else {  # None: an index from before per-component ranges
            c.component: (c.min, c.max) for c in row.component_ranges if c.timeline == timeline
        }
    )
    return ChunkEntry(
        row.chunk_id or b"",
        row.entity_path or "",
        row.is_static,
        row.store_kind == "recording",
        span,
        spans if span is not None else {},
        row.components,
    )


def choose_rows(
    rows: Iterable[IndexRow], entities: EntityFilter, blueprint: bool, keep: set[bytes] | None
) -> Iterator[IndexRow]:
    """The messages a download keeps, in file order (`keep`: the chunk ids of a time window)."""
    for row in rows:
        if row.store_kind == "blueprint" and not blueprint:
            continue
        if row.kind == CHUNK:
            if row.store_kind == "recording" and not entities(row.entity_path or ""):
                continue
            if keep is not None and row.chunk_id not in keep:
                continue
        elif row.kind not in (STORE_INFO, BLUEPRINT_ACTIVATION):
            continue
        yield row


def _reads(rows: Iterable[IndexRow]) -> Iterator[tuple[int, int, list[IndexRow]]]:
    """Ranged reads covering `rows`: (start, end, rows in it), neighbours merged."""
    start = end = -1
    group: list[IndexRow] = []
    limit = FIRST_READ_BYTES
    for row in rows:
        if group and row.offset - end <= GAP_BYTES and row.end - start <= limit:
            end = row.end
            group.append(row)
            continue
        if group:
            yield start, end, group
            limit = min(2 * limit, MAX_READ_BYTES)
        start, end, group = row.offset, row.end, [row]
    if group:
        yield start, end, group


def read_events(recording: IndexedRecording, rows: Iterable[IndexRow], *, header: bool = True) -> Iterator[Event]:
    """The stream's start (unless not `header`), then the messages of `rows` (decoded, their payloads
    left as they are: views of what was read). The stream's header comes with the first messages
    where they are near the start (a sealed run's store info follows it): one read, not a store's
    first byte twice."""
    plans = _reads(rows)
    first = next(plans, None)
    with_header = header and first is not None and first[0] - STREAM_HEADER_SIZE <= GAP_BYTES
    if header and not with_header:
        yield StreamStart(0, 0, decode_stream_header(recording.read(0, STREAM_HEADER_SIZE), 0))
    if first is None:
        return
    plans = itertools.chain([(0, *first[1:]) if with_header else first], plans)

    def read(plan: tuple[int, int, list[IndexRow]]) -> bytes:
        return recording.read(plan[0], plan[1] - plan[0])

    def size(plan: tuple[int, int, list[IndexRow]]) -> int:
        return plan[1] - plan[0]

    for (start, _, group), got in readahead.read_ahead(plans, read, recording.read_ahead, size):
        data = memoryview(got)
        if with_header:
            yield StreamStart(0, 0, decode_stream_header(bytes(data[:STREAM_HEADER_SIZE]), 0))
            with_header = False
        for row in group:
            at = row.offset - start
            kind, length = decode_message_header(data, at)
            payload = data[at + MESSAGE_HEADER_SIZE : at + MESSAGE_HEADER_SIZE + length]
            yield decode_message(kind, payload, row.offset)
