"""Validation of a chunk before it is accepted, and before anything reads its values.

Every chunk a client sends is checked in full at ingest (`check_chunk`): what Rerun itself
requires of its schema (services/rrd/conformance.py), and every value as full Arrow validation
checks it (offsets monotonic and within their child or data, fixed-size list and struct children
long enough, UTF-8), so that every accepted chunk is one Rerun accepts and serves back whole.
pyarrow's cheap `validate()` only compares buffer sizes with lengths: bad offsets or a string that
is not UTF-8 pass it, and reading such values goes out of bounds (a crash of the whole process).
A chunk's values are read by the server in three places: recording properties (ingest), analytics
extraction (Scalars, TextLog, Transform3D) and exact trimming of downloads; each reads them through
`validated_batch`, which validates in full again (stored chunks may predate these checks).
"""

from __future__ import annotations

from contextlib import AbstractContextManager, nullcontext

import pyarrow as pa

from services.rrd import conformance, errors, limits, untrusted
from services.rrd.batch_plan import batch_plan
from services.rrd.chunk import ChunkMeta, decompressed_size, read_chunk
from services.rrd.fieldmeta import component_name, rerun_key
from services.rrd.layout import ENTITY_PATH_KEY, split_ipc
from services.rrd.lz4_prefix import PrefixTooShort
from services.rrd.messages import ArrowMessage, Compression, chunk_id_str
from services.rrd.value_checks import values_valid

_FIX = "the chunk is malformed (Rerun refuses it too, see `rerun rrd verify`); log it again with the Rerun SDK"


def describe(msg: ArrowMessage, entity_path: str | None = None) -> str:
    """`chunk chunk_... of /entity`, as far as known, for error messages."""
    chunk = chunk_id_str(msg.chunk_id) if msg.chunk_id else "without id"
    return f"chunk {chunk}" + (f" of entity {entity_path}" if entity_path else "")


def invalid(msg: ArrowMessage, entity_path: str | None, problem: str) -> errors.InvalidChunkError:
    return errors.InvalidChunkError(f"{describe(msg, entity_path)}: {problem}; {_FIX}", msg.offset)


def check_chunk(msg: ArrowMessage, meta: ChunkMeta) -> None:
    """At ingest, for every chunk: refuse one Rerun would refuse, from its schema (once per schema)
    and its values, fully validated. `chunk_meta` checked most chunks' values already (from the
    record batch's body, or with pyarrow); a large chunk whose metadata came from the first bytes of
    its payload is decompressed whole here (the whole LZ4 block must be sound) and checked the same
    way; where those checks cannot tell, pyarrow's full validation decides."""
    if meta.problem is not None:
        raise invalid(msg, meta.entity_path, meta.problem)
    if meta.values_checked:
        return
    with limits.holding(decompressed_size(msg)):
        try:
            with _payload(msg) as data:
                if _valid_from_body(data, meta):
                    return
                whole = bytes(data)  # for pyarrow, which says why (rare: a damaged chunk)
        except errors.RrdError as exc:
            raise invalid(msg, meta.entity_path, exc.detail) from exc
        validated_batch(msg, meta, whole)


def _payload(msg: ArrowMessage) -> AbstractContextManager[bytes | memoryview]:
    if msg.compression != Compression.LZ4:
        return nullcontext(msg.payload)
    return untrusted.decompressed_view(msg.payload, msg.uncompressed_size, msg.offset)


def _valid_from_body(data: bytes | memoryview, meta: ChunkMeta) -> bool:
    """Whether the whole chunk passes the checks its record batch header allows (`value_checks`)."""
    if not meta.layout.direct:
        return False
    size = len(data)
    head = min(size, _HEAD_BYTES)
    while True:  # the schema and record batch header, as bytes; the values are read from `data`
        prefix = bytes(data[:head])
        try:
            split = split_ipc(prefix, size)
            if split is None:
                return False
            plan = batch_plan(prefix, split[1], meta.layout, size)
            break
        except PrefixTooShort as short:
            head = min(size, max(short.end, 2 * head))
    return plan is not None and plan.checks is not None and values_valid(data, split[1], plan.checks)


_HEAD_BYTES = 64 * 1024  # enough for a chunk's schema and record batch header, but for huge schemas


def validated_batch(msg: ArrowMessage, meta: ChunkMeta | None = None, data: bytes | None = None) -> pa.RecordBatch:
    """The chunk as a record batch, once it is known that every value in it can be read safely;
    else InvalidChunkError naming the chunk, its entity and its byte offset. `data`: its payload
    decompressed already."""
    entity_path = meta.entity_path if meta is not None else None
    try:
        batch = read_chunk(msg, data)
    except errors.RrdError as exc:
        raise invalid(msg, entity_path, exc.detail) from exc
    if entity_path is None:
        entity_path = (batch.schema.metadata or {}).get(ENTITY_PATH_KEY, b"").decode(errors="replace")
    try:
        batch.validate(full=True)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
        raise invalid(msg, entity_path, f"its Arrow data is inconsistent ({exc})") from exc
    if meta is not None:
        problem = meta.problem  # the same checks, made once per schema (and the header's null counts)
    else:
        try:
            problem = _batch_problem(batch)
        except UnicodeDecodeError as exc:
            problem = f"a column name or its metadata is not UTF-8 ({exc})"
    if problem is not None:
        raise invalid(msg, entity_path, problem)
    return batch


def _batch_problem(batch: pa.RecordBatch) -> str | None:
    for i, fld in enumerate(batch.schema):
        metadata = fld.metadata or {}
        component = component_name(fld)
        component_type = rerun_key(metadata, "component_type", b"").decode() or None
        problem = conformance.component_type_problem(component, fld.name, fld.type, component_type)
        if problem is not None:
            return problem
        if not fld.nullable and batch.column(i).null_count:
            return f"column {fld.name!r} is declared non-nullable but holds nulls"
    return None
