"""Chunk metadata from an Arrow message, without copying data columns.

The payload is decompressed (LZ4 block) and read as an Arrow IPC stream zero-copy; only the
schema, the row count, the index (timeline) columns and the data columns' validity are looked at.
A large chunk whose values the server does not read has only the first bytes of its payload
decompressed, those that hold all of that (`PREFIX_FROM_BYTES`, `lz4_prefix`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import lz4.block
import numpy as np
import pyarrow as pa

from services.rrd import errors, limits, lz4_prefix, untrusted
from services.rrd.batch_plan import BatchPlan, batch_plan
from services.rrd.layout import (
    ENTITY_PATH_KEY,
    ChunkLayout,
    DataColumn,
    LayoutCache,
    split_ipc,
)
from services.rrd.lz4_prefix import PrefixTooShort
from services.rrd.messages import ArrowMessage, Compression, chunk_id_str, tuid_proto
from services.rrd.pb import common_pb2, log_msg_pb2
from services.rrd.value_checks import values_valid

CHUNK_ID_KEY = b"rerun:id"
LEGACY_CHUNK_ID_KEY = b"rerun.id"  # SDK 0.23 and older
LEGACY_ENTITY_PATH_KEY = b"rerun.entity_path"


@dataclass(slots=True)
class TimeRange:
    min: int
    max: int


@dataclass(slots=True)
class TimelineMeta:
    name: str
    type: str  # sequence | timestamp | duration
    range: TimeRange
    is_sorted: bool
    field: pa.Field


@dataclass(slots=True)
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


@dataclass(slots=True)
class ChunkMeta:
    chunk_id: bytes
    entity_path: str
    is_static: bool
    num_rows: int
    timelines: tuple[TimelineMeta, ...]
    # Each data column's; None while not asked for, when the chunk is `uniform`: they are then the
    # chunk's rows and ranges, and most chunks are never asked.
    listed_components: tuple[ComponentMeta, ...] | None
    byte_size: int  # the ArrowMsg protobuf, as stored
    uncompressed_size: int  # the Arrow IPC payload once decompressed
    row_id_field: pa.Field | None
    layout: ChunkLayout
    # Why Rerun would refuse this chunk: from its schema and row counts, or its values when they were
    # checked (a chunk read with pyarrow).
    problem: str | None = None
    # Every value passed what full Arrow validation checks (offsets, UTF-8): from the record batch's
    # body (`value_checks`) or by pyarrow. False: not known (a large chunk read from its first bytes,
    # or a check that failed and leaves the verdict to pyarrow, in `validate.check_chunk`).
    values_checked: bool = False
    # Per timeline, over all its rows, when every component holds a value in every row (else None).
    ranges: dict[str, TimeRange] | None = None

    @property
    def uniform(self) -> bool:
        """Every component holds a value in every row: each component's rows and ranges are the chunk's."""
        return self.ranges is not None

    @property
    def components(self) -> tuple[ComponentMeta, ...]:
        if self.listed_components is None:
            rows, ranges = self.num_rows, self.ranges or {}
            self.listed_components = tuple(
                [
                    ComponentMeta(c.column, c.component, c.archetype, c.component_type, rows, ranges, c.field)
                    for c in self.layout.data
                ]
            )
        return self.listed_components

    @property
    def reads_values(self) -> bool:
        """Whether the server reads this chunk's values (so it must be fully validated first)."""
        return self.layout.reads_values

    @property
    def archetypes(self) -> frozenset[str]:
        return self.layout.archetypes

    @property
    def component_names(self) -> frozenset[str]:
        return self.layout.component_names


def decompress_payload(msg: ArrowMessage) -> bytes:
    """The Arrow IPC bytes of `msg`; raises DecompressionError if LZ4 does not give
    exactly `uncompressed_size` bytes."""
    if msg.compression != Compression.LZ4:
        return bytes(msg.payload)
    return untrusted.decompress(msg.payload, msg.uncompressed_size, msg.offset)


def _decompress_prefix(msg: ArrowMessage, size: int) -> bytes:
    untrusted.check_declared_size(msg.uncompressed_size, len(msg.payload), msg.offset)
    try:
        return lz4_prefix.decompress_prefix(msg.payload, size)
    except ValueError as exc:
        raise errors.DecompressionError(
            f"LZ4 block of {len(msg.payload)} bytes does not decompress to the declared "
            f"{msg.uncompressed_size} bytes ({exc})",
            msg.offset,
        ) from exc


def read_chunk(msg: ArrowMessage, data: bytes | None = None) -> pa.RecordBatch:
    """The chunk as an Arrow record batch (zero-copy over the decompressed payload; `data`: that
    payload, decompressed already)."""
    batch = _read_batch(msg, decompress_payload(msg) if data is None else data)
    md = batch.schema.metadata or {}
    if ENTITY_PATH_KEY not in md and LEGACY_ENTITY_PATH_KEY not in md:
        raise errors.NotAChunkError("Arrow schema has no rerun:entity_path metadata", msg.offset)
    return batch


def _read_batch(msg: ArrowMessage, data: bytes) -> pa.RecordBatch:
    try:
        # Message by message rather than `open_stream`: a third less overhead for small chunks.
        reader = pa.BufferReader(pa.py_buffer(data))
        schema = pa.ipc.read_schema(pa.ipc.read_message(reader))
        message = pa.ipc.read_message(reader)
        if untrusted.body_compressed(message):  # pyarrow would allocate whatever its buffers declare
            raise errors.NotAChunkError(
                "its record batch compresses its buffers (IPC body compression), which Rerun never writes",
                msg.offset,
            )
        batch = pa.ipc.read_record_batch(message, schema)
        # Cheap structural check (buffer sizes against lengths), so no later read goes out of bounds.
        batch.validate()
    except (pa.ArrowException, StopIteration, EOFError, OSError, TypeError, ValueError, KeyError) as exc:
        raise errors.NotAChunkError(f"payload is not an Arrow IPC record batch ({exc})", msg.offset) from exc
    return batch


def parse_chunk_id(text: str) -> bytes:
    """`chunk_18EA26BD96404E103c04e43dcbb199d4` -> 16 bytes."""
    return bytes.fromhex(text.removeprefix("chunk_").rjust(32, "0")[-32:])


_LAYOUTS = LayoutCache()
# A chunk this large (decompressed) has its metadata read from the first bytes of its payload
# (`lz4_prefix`), unless the server reads its values: its schema, record batch header, row ids and
# index columns come before its data columns. How many bytes is guessed from the chunk before (a
# stream repeats a few schemas); a chunk that needs more says how much (PrefixTooShort). Its data
# columns are not decompressed: like those of any chunk whose values the server does not read, they
# are the viewer's to read.
PREFIX_FROM_BYTES = 256 * 1024
_PREFIX_MARGIN = 1024
_prefix_guess = 4 * 1024


def decompressed_size(msg: ArrowMessage) -> int:
    return msg.uncompressed_size if msg.compression == Compression.LZ4 else len(msg.payload)


def chunk_meta(msg: ArrowMessage) -> ChunkMeta:
    """Metadata of the chunk in `msg`; raises a codec error if it is not a valid chunk. In worker
    threads, a large chunk's decompressed bytes are counted against the process's budget."""
    global _prefix_guess
    size = decompressed_size(msg)
    partial = msg.compression == Compression.LZ4 and size >= PREFIX_FROM_BYTES and lz4_prefix.available
    want = min(size, _prefix_guess) if partial else size
    while True:
        budget = limits.budget_for(want)
        taken = budget.acquire(want) if budget is not None else 0
        try:
            data = _decompress_prefix(msg, want) if want < size else decompress_payload(msg)
            try:
                meta, needed = _chunk_meta(msg, data, size)
                if partial:
                    _prefix_guess = needed + _PREFIX_MARGIN
                return meta
            except PrefixTooShort as short:
                want = min(size, max(short.end, 2 * want))
            except (UnicodeDecodeError, pa.ArrowInvalid, ValueError) as exc:
                raise errors.NotAChunkError(f"chunk metadata is unreadable ({exc})", msg.offset) from exc
        finally:
            if budget is not None:
                budget.release(taken)


def _chunk_meta(msg: ArrowMessage, data: bytes, size: int) -> tuple[ChunkMeta, int]:
    """The chunk's metadata and how many of the payload's first bytes it took. `data`: the payload
    decompressed, or its first bytes (PrefixTooShort when more are needed)."""
    split = split_ipc(data, size)
    if split is None:
        _whole(data, size)
        _read_batch(msg, data)  # raises the precise error
        raise errors.NotAChunkError("payload is not an Arrow IPC stream", msg.offset)
    schema_message, batch_pos = split
    id_text = chunk_id_str(msg.chunk_id).encode() if msg.chunk_id else b""
    layout = _LAYOUTS.get(schema_message, id_text, msg.offset)
    if layout.reads_values:
        _whole(data, size)  # its values are read: all of it must decompress (and is checked later)
    plan = batch_plan(data, batch_pos, layout, size) if layout.direct else None
    problem = layout.problem
    if plan is not None:
        needed = size if layout.reads_values else batch_pos + plan.reach
        if needed > len(data):
            raise PrefixTooShort(needed)
        num_rows = plan.rows
        ranges = _read_ranges(data, batch_pos, plan) if plan.reads else {}
        components = None  # a plan is made only for chunks without nulls: every component is in every row
        if problem is None and any(plan.null_counts):
            problem = _null_problem(layout, list(plan.null_counts))
        checked = plan.checks is not None and len(data) == size and values_valid(data, batch_pos, plan.checks)
    else:
        _whole(data, size)
        needed = size
        batch = _read_batch(msg, data)
        num_rows, ranges, components = _arrow_values(batch, layout, msg.offset)
        if problem is None:
            problem = _null_problem(layout, [batch.column(i).null_count for i in layout.required])
        # Read with pyarrow anyway (an unusual type or header): its full validation costs little more.
        invalid = _invalid_values(batch)
        checked = invalid is None
        problem = problem or invalid
    timelines = tuple(
        [
            TimelineMeta(ix.name, ix.type, ranges[ix.name], ix.is_sorted, ix.field)
            for ix in layout.indexes
            if ix.name in ranges
        ]
    )
    if msg.chunk_id:
        chunk_id = msg.chunk_id
    else:
        try:
            md = layout.schema.metadata or {}
            chunk_id = parse_chunk_id((md.get(CHUNK_ID_KEY) or md[LEGACY_CHUNK_ID_KEY]).decode())
        except (KeyError, ValueError, UnicodeDecodeError) as exc:
            raise errors.NotAChunkError(f"chunk has no valid rerun:id ({exc})", msg.offset) from exc
    meta = ChunkMeta(
        chunk_id,
        layout.entity_path,
        not layout.indexes,
        num_rows,
        timelines,
        components,
        len(msg.raw),
        msg.uncompressed_size or len(msg.payload),
        layout.row_id_field,
        layout,
        problem,
        checked,
        ranges if components is None else None,
    )
    return meta, needed


def _whole(data: bytes, size: int) -> None:
    """What follows needs the whole payload."""
    if len(data) < size:
        raise PrefixTooShort(size)


def _invalid_values(batch: pa.RecordBatch) -> str | None:
    """Why pyarrow's full validation refuses the batch's values (None: it does not)."""
    try:
        batch.validate(full=True)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
        return f"its Arrow data is inconsistent ({exc})"
    return None


def _null_problem(layout: ChunkLayout, null_counts: list[int]) -> str | None:
    for position, nulls in zip(layout.required, null_counts, strict=True):
        if nulls:
            return f"column {layout.schema.field(position).name!r} is declared non-nullable but holds {nulls} nulls"
    return None


_INT64 = struct.Struct("<q")


def _read_ranges(data: bytes, pos: int, plan: BatchPlan) -> dict[str, TimeRange]:
    """Each timeline's range in the chunk whose record batch starts at `pos`."""
    if plan.one_row is not None:
        firsts = plan.one_row.unpack_from(data, pos + plan.reads[0].first)
        return {read.name: TimeRange(v, v) for read, v in zip(plan.reads, firsts, strict=True)}
    ranges = {}
    for read in plan.reads:
        at = pos + read.first
        if read.is_sorted:
            lo = _INT64.unpack_from(data, at)[0]
            hi = _INT64.unpack_from(data, at + 8 * (read.count - 1))[0] if read.count > 1 else lo
        else:
            values = np.frombuffer(data, dtype="<i8", count=read.count, offset=at)
            lo, hi = int(values.min()), int(values.max())
        ranges[read.name] = TimeRange(lo, hi)
    return ranges


def _arrow_values(
    batch: pa.RecordBatch, layout: ChunkLayout, offset: int
) -> tuple[int, dict[str, TimeRange], tuple[ComponentMeta, ...]]:
    index_values: dict[str, tuple[np.ndarray, TimeRange]] = {}
    for ix in layout.indexes:
        column = batch.column(ix.position)
        values = _int64_values(column)
        if column.null_count:
            values = values[column.is_valid().to_numpy(zero_copy_only=False)].astype(np.int64)
        if len(values) == 0:
            continue
        if ix.is_sorted:
            rng = TimeRange(int(values[0]), int(values[-1]))
        else:
            rng = TimeRange(int(values.min()), int(values.max()))
        index_values[ix.name] = (values, rng)
    components = tuple(_component(c, batch.column(c.position), index_values) for c in layout.data)
    return batch.num_rows, {name: rng for name, (_, rng) in index_values.items()}, components


def _int64_values(column: pa.Array) -> np.ndarray:
    """The int64 storage of an int64/timestamp/duration column, without copying."""
    values = column.view(pa.int64()) if column.type != pa.int64() else column
    array: np.ndarray = values.to_numpy(zero_copy_only=column.null_count == 0, writable=False)
    return array


def _component(
    col: DataColumn, column: pa.Array, index_values: dict[str, tuple[np.ndarray, TimeRange]]
) -> ComponentMeta:
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
    return ComponentMeta(col.column, col.component, col.archetype, col.component_type, num_rows, ranges, col.field)


def with_batch(msg: ArrowMessage, batch: pa.RecordBatch, chunk_id: bytes | None = None) -> ArrowMessage:
    """`msg` holding `batch` instead of its own chunk (re-encoded, LZ4), in the same store. With
    `chunk_id`, the new chunk gets that id (in the Arrow metadata and the message); else it keeps
    its id (the same chunk, e.g. with a secret column removed)."""
    if chunk_id is not None:
        batch = batch.replace_schema_metadata(
            {**(batch.schema.metadata or {}), CHUNK_ID_KEY: chunk_id_str(chunk_id).encode()}
        )
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema) as writer:
        writer.write_batch(batch)
    ipc = sink.getvalue().to_pybytes()
    pb = log_msg_pb2.ArrowMsg.FromString(bytes(msg.raw))
    pb.payload = lz4.block.compress(ipc, store_size=False)
    pb.compression = int(Compression.LZ4)  # type: ignore[assignment]
    pb.uncompressed_size = len(ipc)
    if chunk_id is not None:
        pb.chunk_id.CopyFrom(tuid_proto(chunk_id))
    return ArrowMessage(
        msg.offset,
        msg.stream_offset,
        msg.stream_index,
        pb.SerializeToString(),
        msg.store_id,
        chunk_id or msg.chunk_id,
        msg.is_static,
        Compression.LZ4,
        len(ipc),
        pb.payload,
    )


def with_chunk_id(raw: bytes, chunk_id: bytes, recording_id: str | None = None) -> bytes:
    """A stored ArrowMsg (`raw`, its protobuf) naming its chunk `chunk_id`: the Arrow schema's
    `rerun:id` and the message's `chunk_id` say so, the record batch messages after the schema are
    copied byte for byte (no value is read or re-encoded), the payload LZ4-compressed again. With
    `recording_id`, the message's store id names that recording. NotAChunkError if the payload is
    no IPC stream beginning with a schema."""
    pb = log_msg_pb2.ArrowMsg.FromString(raw)
    ipc = pb.payload
    if pb.compression == int(Compression.LZ4):
        with limits.holding(pb.uncompressed_size):
            ipc = lz4.block.decompress(pb.payload, uncompressed_size=pb.uncompressed_size)
    found = split_ipc(ipc)
    if found is None:
        raise errors.NotAChunkError("the chunk's payload is no Arrow IPC stream", 0)
    _, rest = found
    schema = pa.ipc.read_schema(pa.py_buffer(ipc[:rest]))
    metadata = {k: v for k, v in (schema.metadata or {}).items() if k != LEGACY_CHUNK_ID_KEY}
    named = schema.with_metadata({**metadata, CHUNK_ID_KEY: chunk_id_str(chunk_id).encode()})
    ipc = named.serialize().to_pybytes() + ipc[rest:]
    pb.payload = lz4.block.compress(ipc, store_size=False)
    pb.compression = int(Compression.LZ4)  # type: ignore[assignment]
    pb.uncompressed_size = len(ipc)
    pb.chunk_id.CopyFrom(tuid_proto(chunk_id))
    if recording_id is not None:
        pb.store_id.kind = common_pb2.STORE_KIND_RECORDING
        pb.store_id.recording_id = recording_id
    return pb.SerializeToString()
