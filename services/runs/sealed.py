"""Serving a sealed run (warm, or cold once restored) with ranged reads planned from its chunk index.

`chunks.parquet` says where every message of `recording.rrd` lies, with its entity and time
ranges; a filtered download fetches only the messages it keeps (neighbouring ones in one read),
so a one-entity download of a ten-entity run reads about a tenth of the object. An unfiltered
download is the sealed object itself, copied through.
"""

from __future__ import annotations

from collections.abc import Iterator

from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.decoder import decode_message
from services.rrd.frames import (
    MESSAGE_HEADER_SIZE,
    STREAM_HEADER_SIZE,
    decode_message_header,
    decode_stream_header,
)
from services.rrd.messages import ArrowMessage, Event, StreamStart
from services.runs.download import FLUSH_BYTES, EntityFilter, TimeWindow, encode_run
from services.runs.latest_at import ChunkEntry, pick_rows, select_chunks
from services.sealed.index import BLUEPRINT_ACTIVATION, CHUNK, STORE_INFO, IndexRow
from services.sealed.read import SealedRecording

GAP_BYTES = 64 * 1024  # neighbouring messages closer than this are fetched in one read
MAX_READ_BYTES = 16 * 1024 * 1024  # one read holds at most this much (memory stays bounded)


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


def plan_window(
    sealed: SealedRecording, entities: EntityFilter, window: TimeWindow
) -> tuple[set[bytes], dict[bytes, set[int]]]:
    """The chunk ids a windowed download keeps, and for an exact one the latest-at rows of each chunk:
    only the candidate chunks are read (ranged reads), and with an index from before per-component
    ranges also the chunks whose ranges matter."""
    chunks = [
        r for r in sealed.rows if r.kind == CHUNK and (r.store_kind != "recording" or entities(r.entity_path or ""))
    ]

    def read(ids: set[bytes]) -> Iterator[tuple[ArrowMessage, ChunkMeta]]:
        for event in _events(sealed, [r for r in chunks if r.chunk_id in ids]):
            if isinstance(event, ArrowMessage):
                yield event, chunk_meta(event)

    def resolve(entries: list[ChunkEntry]) -> list[ChunkEntry]:
        metas = {meta.chunk_id: meta for _, meta in read({e.chunk_id for e in entries})}
        return [ChunkEntry.of_meta(metas[e.chunk_id], True, window.timeline) for e in entries if e.chunk_id in metas]

    keep, candidates = select_chunks(
        [_entry(r, window.timeline) for r in chunks], window.bounds, window.latest_at, resolve
    )
    picks = pick_rows(read(candidates), window.timeline, window.bounds[0]) if window.exact and candidates else {}
    return keep, picks


def choose_rows(
    rows: list[IndexRow], entities: EntityFilter, blueprint: bool, keep: set[bytes] | None
) -> list[IndexRow]:
    """The messages a download keeps, in file order (`keep`: the chunk ids of a time window)."""
    chosen = []
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
        chosen.append(row)
    return chosen


def _reads(rows: list[IndexRow]) -> Iterator[tuple[int, int, list[IndexRow]]]:
    """Ranged reads covering `rows`: (start, end, rows in it), neighbours merged."""
    start = end = -1
    group: list[IndexRow] = []
    for row in rows:
        if group and row.offset - end <= GAP_BYTES and row.end - start <= MAX_READ_BYTES:
            end = row.end
            group.append(row)
            continue
        if group:
            yield start, end, group
        start, end, group = row.offset, row.end, [row]
    if group:
        yield start, end, group


def _events(sealed: SealedRecording, rows: list[IndexRow]) -> Iterator[Event]:
    head = sealed.store.get_range(sealed.key, 0, STREAM_HEADER_SIZE)
    yield StreamStart(0, 0, decode_stream_header(head, 0))
    for start, _, group in _reads(rows):
        data = memoryview(sealed.store.get_range(sealed.key, start, group[-1].end - start))
        for row in group:
            at = row.offset - start
            kind, length = decode_message_header(data, at)
            payload = data[at + MESSAGE_HEADER_SIZE : at + MESSAGE_HEADER_SIZE + length]
            yield decode_message(kind, payload, row.offset)


def stream_sealed(
    sealed: SealedRecording, entities: EntityFilter, *, blueprint: bool = True, window: TimeWindow | None = None
) -> Iterator[bytes]:
    if not entities.include and not entities.exclude and blueprint and window is None:
        for start in range(0, sealed.size, FLUSH_BYTES):  # the sealed object is already the answer
            yield sealed.store.get_range(sealed.key, start, min(FLUSH_BYTES, sealed.size - start))
        return
    keep, picks = plan_window(sealed, entities, window) if window is not None else (None, {})
    rows = choose_rows(sealed.rows, entities, blueprint, keep)
    yield from encode_run(
        _events(sealed, rows), entities, blueprint=blueprint, window=window, keep=keep, picks=picks, metas={}
    )
