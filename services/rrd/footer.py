"""Reading a file's RRD footer from its end: the whole chunk index without reading the chunks.

Works for a file holding one stream with a footer (what the SDK's FileSink and our writer
produce). Concatenated streams, files without footer or with a damaged one answer None, and the
caller scans instead.
"""

from __future__ import annotations

import os
from typing import BinaryIO

import pyarrow as pa
import pyarrow.compute as pc
from google.protobuf.message import DecodeError

from services.rrd import errors
from services.rrd.decoder import iter_events
from services.rrd.fieldmeta import component_name, rerun_key
from services.rrd.frames import (
    FOOTER_ENTRY_SIZE,
    FOOTER_FIXED_SIZE,
    FOOTER_MAGIC,
    MESSAGE_HEADER_SIZE,
    STREAM_HEADER_SIZE,
    decode_footer_entry,
    decode_stream_header,
    footer_crc,
)
from services.rrd.layout import timeline_type
from services.rrd.manifest import read_manifest, read_sorbet_schema
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    StoreId,
    StoreInfoMessage,
    StreamStart,
)
from services.rrd.pb import log_msg_pb2
from services.rrd.summary import EntitySummary, RrdSummary, StoreSummary, TimelineSummary

_TRAILER = FOOTER_ENTRY_SIZE + FOOTER_FIXED_SIZE
_STORE_INFO_SCAN_LIMIT = 64 * 1024 * 1024


def read_footer(fh: BinaryIO) -> log_msg_pb2.RrdFooter | None:
    """The footer of a single-stream file, checked (position, length, CRC); None if unusable."""
    size = fh.seek(0, os.SEEK_END)
    if size < STREAM_HEADER_SIZE + MESSAGE_HEADER_SIZE + _TRAILER:
        return None
    fh.seek(size - _TRAILER)
    trailer = fh.read(_TRAILER)
    if trailer[FOOTER_ENTRY_SIZE : FOOTER_ENTRY_SIZE + 8] != FOOTER_MAGIC or trailer[-4:] != b"\x01\0\0\0":
        return None
    start, length, crc = decode_footer_entry(trailer)
    # One stream starting at byte 0: its End payload runs right up to the trailer.
    if start + length + _TRAILER != size or start < STREAM_HEADER_SIZE + MESSAGE_HEADER_SIZE:
        return None
    fh.seek(0)
    try:
        decode_stream_header(fh.read(STREAM_HEADER_SIZE), 0)
    except errors.RrdError:
        return None
    fh.seek(start)
    payload = fh.read(length)
    if len(payload) != length or footer_crc(payload) != crc:
        return None
    try:
        return log_msg_pb2.RrdFooter.FromString(payload)
    except DecodeError:
        return None


def summarize_from_footer(path: str) -> RrdSummary | None:
    """A summary of `path` from its footer plus the store infos at its start; None if the file has
    no usable footer (then scan it with `summarize`)."""
    with open(path, "rb") as fh:
        footer = read_footer(fh)
        if footer is None or not footer.manifests:
            return None
        try:
            summary = RrdSummary(path, bytes_read=fh.seek(0, os.SEEK_END), streams=1, footers=1, index="footer")
            for manifest in footer.manifests:
                _add_manifest(summary, manifest)
        except (pa.ArrowInvalid, KeyError, ValueError, DecodeError):
            return None
        fh.seek(0)
        _add_store_infos(summary, fh)
    return summary


def _add_store_infos(summary: RrdSummary, fh: BinaryIO) -> None:
    """Read the leading messages: every store's SetStoreInfo, and blueprint activations (the SDK
    sends a blueprint whole before the recording's first chunk), in stream order."""
    missing = set(summary.stores)
    order: list[StoreId] = []
    try:
        for event in iter_events(fh):
            if isinstance(event, StreamStart):
                summary.rerun_versions.append(str(event.version))
            elif isinstance(event, StoreInfoMessage):
                summary.add_store_info(event)
                missing.discard(event.store_id)
                if event.store_id not in order:
                    order.append(event.store_id)
            elif isinstance(event, BlueprintActivationMessage):
                summary.store(event.blueprint_id).blueprint_activations += 1
            elif isinstance(event, ArrowMessage) and not missing and not event.store_id.is_blueprint:
                break
            if event.offset > _STORE_INFO_SCAN_LIMIT:
                break
    except errors.RrdError:
        pass
    stores = summary.stores
    summary.stores = {sid: stores[sid] for sid in order + [sid for sid in stores if sid not in order]}


def _add_manifest(summary: RrdSummary, manifest: log_msg_pb2.RrdManifest) -> None:
    table = read_manifest(manifest)
    schema = read_sorbet_schema(manifest)
    store = summary.store(StoreId.from_proto(manifest.store_id))
    paths = table.column("chunk_entity_path").to_pylist()
    rows = table.column("chunk_num_rows").to_pylist()
    sizes = table.column("chunk_byte_size").to_pylist()
    static = table.column("chunk_is_static").to_pylist()
    for path, n, size, is_static in zip(paths, rows, sizes, static, strict=True):
        entity = store.entities.get(path)
        if entity is None:
            entity = store.entities[path] = EntitySummary(path)
        entity.chunks += 1
        entity.static_chunks += bool(is_static)
        entity.rows += n
        entity.bytes += size
    store.chunks += len(paths)
    store.rows += sum(rows)
    store.bytes += sum(sizes)
    _add_columns(store, schema)
    _add_timelines(store, schema, table)


def _add_columns(store: StoreSummary, schema: pa.Schema) -> None:
    for fld in schema:
        entity_path = rerun_key(fld, "entity_path")
        if rerun_key(fld, "kind") != b"data" or entity_path is None:
            continue
        entity = store.entities.get(entity_path.decode())
        if entity is None:
            continue
        entity.components.add(component_name(fld))
        archetype = rerun_key(fld, "archetype")
        if archetype is not None:
            entity.archetypes.add(archetype.decode())


def _add_timelines(store: StoreSummary, schema: pa.Schema, table: pa.Table) -> None:
    for fld in schema:
        if rerun_key(fld, "kind") != b"index":
            continue
        name = rerun_key(fld, "index_name", fld.name.encode()).decode()
        type_name = timeline_type(fld.type)
        starts = [
            c
            for c in table.schema
            if c.name.endswith(":start")
            and c.metadata
            and rerun_key(c, "index") == name.encode()
            and rerun_key(c, "component") is None
        ]
        if type_name is None or not starts:
            continue
        start_col = table.column(starts[0].name)
        end_col = table.column(starts[0].name[: -len("start")] + "end")
        lo = pc.min(start_col.cast(pa.int64()) if start_col.type != pa.int64() else start_col).as_py()
        hi = pc.max(end_col.cast(pa.int64()) if end_col.type != pa.int64() else end_col).as_py()
        if lo is None or hi is None:
            continue
        known = store.timelines.get(name)
        if known is None:
            store.timelines[name] = TimelineSummary(name, type_name, lo, hi)
        else:
            known.min, known.max = min(known.min, lo), max(known.max, hi)
