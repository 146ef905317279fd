"""Serving a run file by decoding every chunk, without its chunk index: how hot downloads were
served before the index, kept as the reference the indexed path's bytes are compared with."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from services.hot.read import read_events
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.messages import ArrowMessage, StoreKind
from services.runs.download import EntityFilter, TimeWindow, encode_run
from services.runs.latest_at import ChunkEntry, pick_rows, select_chunks


def stream_run(
    path: Path, size: int, entities: EntityFilter, *, blueprint: bool = True, window: TimeWindow | None = None
) -> Iterator[bytes | memoryview]:
    """The run in `path` (its first `size` bytes) as an RRD stream, every chunk's metadata read from
    its payload: the reference the indexed path (`services.runs.indexed.stream_hot`) must match."""
    metas: dict[int, ChunkMeta] = {}  # by frame offset
    keep: set[bytes] | None = None
    picks: dict[bytes, set[int]] = {}  # exact: chunk id -> its rows kept as latest-at rows
    if window is not None:  # a first pass picks the chunks; payloads are only read in the second
        found = []
        for first in read_events(path, size):
            if isinstance(first, ArrowMessage):
                meta = metas[first.offset] = chunk_meta(first)
                recording = first.store_id.kind == StoreKind.RECORDING
                if not recording or entities(meta.entity_path):
                    found.append(ChunkEntry.of_meta(meta, recording, window.timeline))
        keep, candidates = select_chunks(found, window.bounds, window.latest_at, resolve=lambda known: known)
        if window.exact and candidates:
            picks = pick_rows(chunks_of(path, size, metas, candidates), window.timeline, window.bounds[0])
    yield from encode_run(
        read_events(path, size), entities, blueprint=blueprint, window=window, keep=keep, picks=picks, metas=metas
    )


def chunks_of(
    path: Path, size: int, metas: dict[int, ChunkMeta], chunk_ids: set[bytes]
) -> Iterator[tuple[ArrowMessage, ChunkMeta]]:
    for event in read_events(path, size):
        if isinstance(event, ArrowMessage) and (meta := metas[event.offset]).chunk_id in chunk_ids:
            yield event, meta
