"""Chunk metadata from an Arrow message, without copying data columns.

The payload is decompressed (LZ4 block) and read as an Arrow IPC stream zero-copy; only the
schema, the row count, the index (timeline) columns and the data columns' validity are looked at.
"""

from __future__ import annotations

from dataclasses import dataclass

import lz4.block
import numpy as np
import pyarrow as pa

from services.rrd import errors
from services.rrd.messages import ArrowMessage, Compression

ENTITY_PATH_KEY = b"rerun:entity_path"
CHUNK_ID_KEY = b"rerun:id"
KIND_KEY = b"rerun:kind"
INDEX_NAME_KEY = b"rerun:index_name"
IS_SORTED_KEY = b"rerun:is_sorted"
ARCHETYPE_KEY = b"rerun:archetype"
COMPONENT_KEY = b"rerun:component"
COMPONENT_TYPE_KEY = b"rerun:component_type"

# Rerun accepts both the current and the legacy names of column kinds.
_CONTROL_KINDS = (b"control", b"row_id")
_INDEX_KINDS = (b"index", b"time")

_LZ4_MAX_RATIO = 255

TIMELINE_TYPES = {"int64": "sequence", "timestamp": "timestamp", "duration": "duration"}


@dataclass(frozen=True, slots=True)
class TimeRange:
    min: int
    max: int


@dataclass(frozen=True, slots=True)
class TimelineMeta:
    name: str
    type: str  # sequence | timestamp | duration
    range: TimeRange
    is_sorted: bool
    field: pa.Field


@dataclass(frozen=True, slots=True)
class ComponentMeta:
    column: str  # the chunk's column name, e.g. "Points3D:positions"
    component: str  # rerun:component
    archetype: str | None
    component_type: str | None
    num_rows: int  # rows where the component is not null
    ranges: dict[str, TimeRange]  # per timeline, over the rows where it is not null
    field: pa.Field

    @property
    def descriptor(self) -> tuple[str, str, str]:
        return (self.archetype or "", self.component, self.component_type or "")


@dataclass(frozen=True, slots=True)
class ChunkMeta:
    chunk_id: bytes
    entity_path: str
    is_static: bool
    num_rows: int
    timelines: tuple[TimelineMeta, ...]
    components: tuple[ComponentMeta, ...]
    byte_size: int  # the ArrowMsg protobuf, as stored
    uncompressed_size: int  # the Arrow IPC payload once decompressed
    row_id_field: pa.Field | None

    @property
    def archetypes(self) -> set[str]:
        return {c.archetype for c in self.components if c.archetype}


def decompress_payload(msg: ArrowMessage) -> bytes:
    """The Arrow IPC bytes of `msg`; raises DecompressionError if LZ4 does not give
    exactly `uncompressed_size` bytes."""
    if msg.compression != Compression.LZ4:
        return msg.payload
    if msg.uncompressed_size > _LZ4_MAX_RATIO * len(msg.payload) + 64:
        # Refuse before allocating: no LZ4 block expands more than ~255x.
        raise errors.DecompressionError(
            f"LZ4 block of {len(msg.payload)} bytes cannot decompress to the declared "
            f"{msg.uncompressed_size} bytes", msg.offset,
        )
    try:
        data: bytes = lz4.block.decompress(msg.payload, uncompressed_size=msg.uncompressed_size)
    except (lz4.block.LZ4BlockError, ValueError, MemoryError, OverflowError) as exc:
        raise errors.DecompressionError(
            f"LZ4 block of {len(msg.payload)} bytes does not decompress to the declared "
            f"{msg.uncompressed_size} bytes ({exc})", msg.offset,
        ) from exc
    if len(data) != msg.uncompressed_size:
        raise errors.DecompressionError(
            f"LZ4 block decompressed to {len(data)} bytes, declared {msg.uncompressed_size}", msg.offset
        )
    return data


def read_chunk(msg: ArrowMessage) -> pa.RecordBatch:
    """The chunk as an Arrow record batch (zero-copy over the decompressed payload)."""
    data = decompress_payload(msg)
    try:
        # Message by message rather than `open_stream`: a third less overhead for 1-row chunks.
        reader = pa.BufferReader(pa.py_buffer(data))
        schema = pa.ipc.read_schema(pa.ipc.read_message(reader))
        batch = pa.ipc.read_record_batch(pa.ipc.read_message(reader), schema)
        # Cheap structural check (buffer sizes against lengths), so no later read goes out of bounds.
        batch.validate()
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError, StopIteration, EOFError, OSError, TypeError) as exc:
        raise errors.NotAChunkError(f"payload is not an Arrow IPC record batch ({exc})", msg.offset) from exc
    metadata = batch.schema.metadata or {}
    if ENTITY_PATH_KEY not in metadata:
        raise errors.NotAChunkError("Arrow schema has no rerun:entity_path metadata", msg.offset)
    return batch


def parse_chunk_id(text: str) -> bytes:
    """`chunk_18EA26BD96404E103c04e43dcbb199d4` -> 16 bytes."""
    return bytes.fromhex(text.removeprefix("chunk_").rjust(32, "0")[-32:])


def chunk_meta(msg: ArrowMessage) -> ChunkMeta:
    """Metadata of the chunk in `msg`; raises a codec error if it is not a valid chunk."""
    batch = read_chunk(msg)
    try:
        return _chunk_meta(msg, batch)
    except (UnicodeDecodeError, pa.ArrowInvalid, ValueError) as exc:
        raise errors.NotAChunkError(f"chunk metadata is unreadable ({exc})", msg.offset) from exc


def _chunk_meta(msg: ArrowMessage, batch: pa.RecordBatch) -> ChunkMeta:
    schema = batch.schema
    metadata = schema.metadata or {}
    try:
        entity_path = metadata[ENTITY_PATH_KEY].decode()
        chunk_id = msg.chunk_id or parse_chunk_id(metadata[CHUNK_ID_KEY].decode())
    except (KeyError, ValueError, UnicodeDecodeError) as exc:
        raise errors.NotAChunkError(f"chunk has no valid rerun:id or entity path ({exc})", msg.offset) from exc
    timelines: list[TimelineMeta] = []
    index_values: dict[str, tuple[np.ndarray, TimeRange]] = {}
    components: list[ComponentMeta] = []
    row_id_field = None
    data_columns = []
    for i, fld in enumerate(schema):
        fmeta = fld.metadata or {}
        kind = fmeta.get(KIND_KEY)
        if kind in _CONTROL_KINDS:
            row_id_field = fld
        elif kind in _INDEX_KINDS:
            timeline = _timeline(fld, batch.column(i), msg.offset)
            if timeline is not None:
                timelines.append(timeline[0])
                index_values[timeline[0].name] = (timeline[1], timeline[0].range)
        else:
            data_columns.append(i)
    for i in data_columns:
        components.append(_component(schema.field(i), batch.column(i), index_values))
    is_static = not timelines
    return ChunkMeta(
        chunk_id=chunk_id,
        entity_path=entity_path,
        is_static=is_static,
        num_rows=batch.num_rows,
        timelines=tuple(timelines),
        components=tuple(components),
        byte_size=msg.size,
        uncompressed_size=msg.uncompressed_size or len(msg.payload),
        row_id_field=row_id_field,
    )


def _int64_values(column: pa.Array) -> np.ndarray:
    """The int64 storage of an int64/timestamp/duration column, without copying."""
    values = column.view(pa.int64()) if column.type != pa.int64() else column
    array: np.ndarray = values.to_numpy(zero_copy_only=column.null_count == 0, writable=False)
    return array


def _timeline(fld: pa.Field, column: pa.Array, offset: int) -> tuple[TimelineMeta, np.ndarray] | None:
    type_name = TIMELINE_TYPES.get(str(fld.type).split("[")[0])
    if type_name is None:
        raise errors.NotAChunkError(f"index column {fld.name!r} has unsupported type {fld.type}", offset)
    fmeta = fld.metadata or {}
    name = fmeta.get(INDEX_NAME_KEY, fld.name.encode()).decode()
    values = _int64_values(column)
    if column.null_count:
        values = values[column.is_valid().to_numpy(zero_copy_only=False)].astype(np.int64)
    if len(values) == 0:
        return None
    is_sorted = fmeta.get(IS_SORTED_KEY) == b"true"
    if is_sorted:
        lo, hi = int(values[0]), int(values[-1])
    else:
        lo, hi = int(values.min()), int(values.max())
    return TimelineMeta(name, type_name, TimeRange(lo, hi), is_sorted, fld), values


def _component(fld: pa.Field, column: pa.Array,
               index_values: dict[str, tuple[np.ndarray, TimeRange]]) -> ComponentMeta:
    fmeta = fld.metadata or {}
    archetype = fmeta.get(ARCHETYPE_KEY)
    component_type = fmeta.get(COMPONENT_TYPE_KEY)
    component = fmeta.get(COMPONENT_KEY, fld.name.encode()).decode()
    ranges: dict[str, TimeRange] = {}
    if column.null_count == 0:
        num_rows = len(column)
        for name, (values, full_range) in index_values.items():
            if len(values) == num_rows and num_rows:
                ranges[name] = full_range
    else:
        mask = column.is_valid().to_numpy(zero_copy_only=False)
        num_rows = int(mask.sum())
        for name, (values, _) in index_values.items():
            if len(values) == len(mask) and num_rows:
                picked = values[mask]
                ranges[name] = TimeRange(int(picked.min()), int(picked.max()))
    return ComponentMeta(
        column=fld.name,
        component=component,
        archetype=archetype.decode() if archetype else None,
        component_type=component_type.decode() if component_type else None,
        num_rows=num_rows,
        ranges=ranges,
        field=fld,
    )
