"""What a hot run's chunk index must say, worked out independently: every message of a run file
decoded from the file, each chunk's metadata read from its Arrow payload."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pyarrow as pa

from services.hot.index import HotEntry
from services.hot.store import HotRun
from services.rrd import iter_events
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.chunk_index import BLUEPRINT_ACTIVATION, CHUNK, STORE_INFO, IndexRow, store_kind_name
from services.rrd.frames import MESSAGE_HEADER_SIZE
from services.rrd.manifest import ManifestEntry, build_manifest, read_manifest, read_sorbet_schema
from services.rrd.messages import ArrowMessage, BlueprintActivationMessage, StoreId, StoreInfoMessage, StoreKind


def expected_entries(path: Path) -> list[HotEntry]:
    """The entries of a run file, from the file alone."""
    entries = []
    for event in iter_events(path):
        if isinstance(event, ArrowMessage):
            meta = chunk_meta(event)
            length = MESSAGE_HEADER_SIZE + len(event.raw)
            entries.append(HotEntry(CHUNK, store_kind_name(event.store_id.kind), event.offset, length, meta))
        elif isinstance(event, StoreInfoMessage):
            kind = store_kind_name(event.store_id.kind)
            entries.append(HotEntry(STORE_INFO, kind, event.offset, MESSAGE_HEADER_SIZE + len(event.raw)))
        elif isinstance(event, BlueprintActivationMessage):
            length = MESSAGE_HEADER_SIZE + len(event.raw)
            entries.append(HotEntry(BLUEPRINT_ACTIVATION, "blueprint", event.offset, length))
    return entries


def _field(f: pa.Field) -> tuple[str, str, bool, Any]:
    return f.name, str(f.type), f.nullable, f.metadata


def meta_key(meta: ChunkMeta | None) -> Any:
    """What a chunk's metadata says, as comparable values (its layout object aside)."""
    if meta is None:
        return None
    return (
        meta.chunk_id,
        meta.entity_path,
        meta.is_static,
        meta.num_rows,
        [(t.name, t.type, t.range, t.is_sorted, _field(t.field)) for t in meta.timelines],
        [
            (c.column, c.component, c.archetype, c.component_type, c.num_rows, c.ranges, _field(c.field))
            for c in meta.components
        ],
        meta.byte_size,
        meta.uncompressed_size,
        None if meta.row_id_field is None else _field(meta.row_id_field),
    )


def entry_keys(entries: list[HotEntry]) -> list[tuple[IndexRow, Any]]:
    return [(e.row, meta_key(e.meta)) for e in entries]


def manifest_of(entries: list[HotEntry], store: StoreId) -> tuple[pa.Table, pa.Schema, bytes]:
    """The footer manifest of the recording's chunks (table, sorbet schema, its SHA-256)."""
    chunks = [
        ManifestEntry(e.meta, e.offset + MESSAGE_HEADER_SIZE)
        for e in entries
        if e.meta is not None and e.store_kind == "recording"
    ]
    manifest = build_manifest(store, chunks)
    return read_manifest(manifest), read_sorbet_schema(manifest), manifest.sorbet_schema_sha256


def append_recording(run: HotRun, path: Path, *, with_meta: bool = True, limit: int | None = None) -> int:
    """Append the messages of a recording to a hot run as ingest does (SetStoreInfo, chunks with
    their metadata, blueprint activations); returns how many were appended."""
    count = 0
    for event in iter_events(path):
        if limit is not None and count >= limit:
            break
        if isinstance(event, ArrowMessage):
            run.append(event.kind, event.raw, event.store_id.kind, chunk_meta(event) if with_meta else None)
        elif isinstance(event, StoreInfoMessage):
            run.append(event.kind, event.raw, event.store_id.kind)
        elif isinstance(event, BlueprintActivationMessage):
            run.append(event.kind, event.raw, StoreKind.BLUEPRINT)
        else:
            continue
        count += 1
    return count
