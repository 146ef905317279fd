"""Sealing: a run's recording(s) rewritten as one compacted `.rrd` with a footer, plus its index.

The sealed recording is one stream: the run's SDK version in the header, each store's
SetStoreInfo once, every chunk once (by chunk id), blueprint activations once, in the order
they were received, then End with a footer manifest. Hashed as it is written, so the catalog can
record what was stored; written straight into the store as it is made (`services/sealed/upload.py`).
"""

from __future__ import annotations

import datetime as dt
import hashlib
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import BinaryIO, cast

from services.facts.identity import DEFAULT_SECRETS, SecretFields
from services.facts.run import RunFacts
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.chunk_index import chunk_row
from services.rrd.encoder import RrdEncoder
from services.rrd.frames import DEFAULT_VERSION
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    Event,
    StoreId,
    StoreInfoMessage,
    StoreKind,
    StreamStart,
)
from services.sealed.index import BLUEPRINT_ACTIVATION, STORE_INFO, IndexRow, to_parquet

RECORDING = "recording.rrd"
INDEX = "chunks.parquet"
RUN_JSON = "run.json"


class HashingFile:
    """A file being written whose SHA-256 is computed on the way."""

    def __init__(self, fh: BinaryIO) -> None:
        self._fh = fh
        self.sha256 = hashlib.sha256()
        self.size = 0

    def write(self, data: bytes) -> int:
        self.sha256.update(data)
        self.size += len(data)
        return self._fh.write(data)


@dataclass
class SealedRun:
    recording_sha256: str
    recording_size: int
    index_rows: list[IndexRow]
    facts: RunFacts
    index: bytes = b""  # chunks.parquet
    index_sha256: str = ""
    chunk_ids: set[bytes] = field(default_factory=set)

    def __post_init__(self) -> None:
        self.index = to_parquet(self.index_rows)
        self.index_sha256 = hashlib.sha256(self.index).hexdigest()


def _store_kind(store: StoreId) -> str:
    return "blueprint" if store.kind == StoreKind.BLUEPRINT else "recording"


def seal(
    recordings: Iterable[Iterator[Event]],
    out: BinaryIO,
    run_id: str,
    now: dt.datetime,
    on_chunk: Callable[[ArrowMessage, ChunkMeta], None] | None = None,
    secret_fields: SecretFields = DEFAULT_SECRETS,
) -> SealedRun:
    """Write `out` (recording.rrd, front to back) from the events of one or more recordings of the
    same run (a sealed recording and what came after it); returns where every message went and the
    run's facts.
    `on_chunk` sees every recording chunk kept (analytics extraction rides on this one pass);
    `secret_fields`, the node's setting, is what reading property values leaves out."""
    facts = RunFacts(run_id, now, secret_fields)
    rows: list[IndexRow] = []
    seen_chunks: set[bytes] = set()
    seen_stores: set[StoreId] = set()
    seen_activations: set[bytes] = set()
    sink = HashingFile(out)
    encoder: RrdEncoder | None = None
    for events in recordings:
        for event in events:
            if isinstance(event, StreamStart):
                encoder = encoder or RrdEncoder(cast(BinaryIO, sink), event.version)
                continue
            if not isinstance(event, StoreInfoMessage | ArrowMessage | BlueprintActivationMessage):
                continue  # End and footers of a sealed recording being extended
            encoder = encoder or RrdEncoder(cast(BinaryIO, sink), DEFAULT_VERSION)
            start = encoder.position
            if isinstance(event, StoreInfoMessage):
                if event.store_id in seen_stores:
                    continue
                seen_stores.add(event.store_id)
                encoder.write(event)
                rows.append(IndexRow(STORE_INFO, _store_kind(event.store_id), start, encoder.position - start))
            elif isinstance(event, BlueprintActivationMessage):
                if bytes(event.raw) in seen_activations:
                    continue
                seen_activations.add(bytes(event.raw))
                encoder.write(event)
                rows.append(IndexRow(BLUEPRINT_ACTIVATION, "blueprint", start, encoder.position - start))
            else:
                meta = chunk_meta(event)
                if meta.chunk_id in seen_chunks:
                    continue
                seen_chunks.add(meta.chunk_id)
                encoder.write_arrow(event, meta)
                if on_chunk is not None and event.store_id.kind == StoreKind.RECORDING:
                    on_chunk(event, meta)
                rows.append(chunk_row(_store_kind(event.store_id), start, encoder.position - start, meta))
            facts.replay(event, now, meta if isinstance(event, ArrowMessage) else None)
    (encoder or RrdEncoder(cast(BinaryIO, sink), DEFAULT_VERSION)).finish()
    facts.size = sink.size
    return SealedRun(sink.sha256.hexdigest(), sink.size, rows, facts, chunk_ids=seen_chunks)
