"""Serving a sealed run (warm, or cold once restored) with ranged reads planned from its chunk index.

`chunks.parquet` says where every message of `recording.rrd` lies, with its entity and time
ranges; a filtered download fetches only the messages it keeps (neighbouring ones in one read),
so a one-entity download of a ten-entity run reads about a tenth of the object. An unfiltered
download is the sealed object itself, copied through.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from dataclasses import dataclass

from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from services.errors import ErrorCode, FleetError
from services.retention.index import BLUEPRINT_ACTIVATION, CHUNK, STORE_INFO, IndexRow, from_parquet
from services.retention.seal import INDEX, RECORDING
from services.retention.tiers import readable_when_cold
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
from services.runs.service import run_not_found
from services.storage.objectstore import ObjectStore

GAP_BYTES = 64 * 1024  # neighbouring messages closer than this are fetched in one read
MAX_READ_BYTES = 16 * 1024 * 1024  # one read holds at most this much (memory stays bounded)


@dataclass(frozen=True)
class SealedRecording:
    store: ObjectStore
    prefix: str
    size: int  # of recording.rrd
    rows: list[IndexRow]

    @property
    def key(self) -> str:
        return f"{self.prefix}/{RECORDING}"

    def timeline_types(self) -> dict[str, str]:
        return {t.name: t.type for r in self.rows if r.kind == CHUNK for t in r.timelines}


class RunArchivedError(FleetError):
    code = ErrorCode.CONFLICT


class RunDeletedError(FleetError):
    code = ErrorCode.GONE


def _when(value: dt.datetime | None) -> str:
    return value.strftime("%Y-%m-%d %H:%M UTC") if value is not None else "an unknown time"


def locate_sealed(catalog: sessionmaker[Session], warm: ObjectStore, run_id: str,
                  now: dt.datetime) -> SealedRecording:
    """Where a run that left the hot tier can be read: the warm store (cold runs once restored).
    A cold run not restored is a CONFLICT saying how to restore it; a deleted one is GONE."""
    with session_scope(catalog) as session:
        run = queries.get_run(session, run_id)
        life = queries.lifecycle(session, run_id)
        if run is None or life is None:
            raise run_not_found(run_id)
        if run.tier == "deleted":
            raise RunDeletedError(f"run {run_id!r} was deleted on {_when(life.deleted_at)} by {life.deleted_by}"
                                  + (f" (retention policy {life.deleted_policy!r})" if life.deleted_policy else ""))
        restored = readable_when_cold(life.archive_mode) or (
            life.restore_state == "restored" and (life.restore_until is None or
                                                  queries.aware(life.restore_until) > now))
        if run.tier == "cold" and not restored:
            doing = (f"a restore was asked for at {_when(life.restore_requested_at)} and is under way: try again "
                     "later" if life.restore_state == "restoring" else
                     f"restore it with POST /v1/runs/{run_id}/restore or `fleet runs restore {run_id}`")
            raise RunArchivedError(f"run {run_id!r} is archived in the cold tier since {_when(life.archived_at)}; "
                                   f"{doing}")
        prefix = life.prefix
    return open_sealed(warm, prefix)


def open_sealed(store: ObjectStore, prefix: str) -> SealedRecording:
    rows = from_parquet(store.get_range(f"{prefix}/{INDEX}"))
    return SealedRecording(store, prefix, store.head(f"{prefix}/{RECORDING}").size, rows)


def _entry(row: IndexRow, timeline: str) -> ChunkEntry:
    span = next(((t.min, t.max) for t in row.timelines if t.name == timeline), None)
    spans = None if row.component_ranges is None else {  # None: an index from before per-component ranges
        c.component: (c.min, c.max) for c in row.component_ranges if c.timeline == timeline}
    return ChunkEntry(row.chunk_id or b"", row.entity_path or "", row.is_static, row.store_kind == "recording",
                      span, spans if span is not None else {}, row.components)


def plan_window(sealed: SealedRecording, entities: EntityFilter,
                window: TimeWindow) -> tuple[set[bytes], dict[bytes, set[int]]]:
    """The chunk ids a windowed download keeps, and for an exact one the latest-at rows of each chunk:
    only the candidate chunks are read (ranged reads), and with an index from before per-component
    ranges also the chunks whose ranges matter."""
    chunks = [r for r in sealed.rows if r.kind == CHUNK and (r.store_kind != "recording"
                                                             or entities(r.entity_path or ""))]

    def read(ids: set[bytes]) -> Iterator[tuple[ArrowMessage, ChunkMeta]]:
        for event in _events(sealed, [r for r in chunks if r.chunk_id in ids]):
            if isinstance(event, ArrowMessage):
                yield event, chunk_meta(event)

    def resolve(entries: list[ChunkEntry]) -> list[ChunkEntry]:
        metas = {meta.chunk_id: meta for _, meta in read({e.chunk_id for e in entries})}
        return [ChunkEntry.of_meta(metas[e.chunk_id], True, window.timeline) for e in entries if e.chunk_id in metas]

    keep, candidates = select_chunks([_entry(r, window.timeline) for r in chunks], window.bounds,
                                     window.latest_at, resolve)
    picks = pick_rows(read(candidates), window.timeline, window.bounds[0]) if window.exact and candidates else {}
    return keep, picks


def choose_rows(rows: list[IndexRow], entities: EntityFilter, blueprint: bool,
                keep: set[bytes] | None) -> list[IndexRow]:
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


def _events(sealed: SealedRecording, rows: list[IndexRow]) -> Iterator[Event | None]:
    head = sealed.store.get_range(sealed.key, 0, STREAM_HEADER_SIZE)
    yield StreamStart(0, 0, decode_stream_header(head, 0))
    for start, _, group in _reads(rows):
        data = memoryview(sealed.store.get_range(sealed.key, start, group[-1].end - start))
        for row in group:
            at = row.offset - start
            kind, length = decode_message_header(data, at)
            payload = data[at + MESSAGE_HEADER_SIZE: at + MESSAGE_HEADER_SIZE + length]
            yield decode_message(kind, payload, row.offset)


def stream_sealed(sealed: SealedRecording, entities: EntityFilter, *, blueprint: bool = True,
                  window: TimeWindow | None = None) -> Iterator[bytes]:
    if not entities.include and not entities.exclude and blueprint and window is None:
        for start in range(0, sealed.size, FLUSH_BYTES):  # the sealed object is already the answer
            yield sealed.store.get_range(sealed.key, start, min(FLUSH_BYTES, sealed.size - start))
        return
    keep, picks = plan_window(sealed, entities, window) if window is not None else (None, {})
    rows = choose_rows(sealed.rows, entities, blueprint, keep)
    yield from encode_run(_events(sealed, rows), entities, blueprint=blueprint, window=window, keep=keep,
                          picks=picks, metas={})
