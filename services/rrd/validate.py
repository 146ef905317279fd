"""Validation of a chunk before anything reads its values.

`chunk_meta` reads only the schema and the record batch header; a chunk's values are read by the
server in three places: recording properties (ingest), analytics extraction (Scalars, TextLog,
Transform3D) and exact trimming of downloads. pyarrow's cheap `validate()` only compares buffer
sizes with lengths: bad list offsets, a string that is not UTF-8 or a child array shorter than its
offsets say pass it, and reading such values goes out of bounds (a crash of the whole process). So
every chunk whose values are read is first validated fully (`validate(full=True)`: offsets
monotonic and within the child, fixed-size list and struct children lengths, UTF-8) and checked
against what Rerun itself requires (see services/rrd/conformance.py).
"""

from __future__ import annotations

import pyarrow as pa

from services.rrd import conformance, errors
from services.rrd.chunk import ChunkMeta, read_chunk
from services.rrd.layout import ENTITY_PATH_KEY
from services.rrd.messages import ArrowMessage, chunk_id_str

_FIX = "the chunk is malformed (Rerun refuses it too, see `rerun rrd verify`); log it again with the Rerun SDK"


def describe(msg: ArrowMessage, entity_path: str | None = None) -> str:
    """`chunk chunk_... of /entity`, as far as known, for error messages."""
    chunk = chunk_id_str(msg.chunk_id) if msg.chunk_id else "without id"
    return f"chunk {chunk}" + (f" of entity {entity_path}" if entity_path else "")


def invalid(msg: ArrowMessage, entity_path: str | None, problem: str) -> errors.InvalidChunkError:
    return errors.InvalidChunkError(f"{describe(msg, entity_path)}: {problem}; {_FIX}", msg.offset)


def check_chunk(msg: ArrowMessage, meta: ChunkMeta) -> None:
    """At ingest: refuse a chunk Rerun would refuse (from its schema and header: cheap), and fully
    validate a chunk whose values the server will read (analytics components): with pyarrow, unless
    `chunk_meta` could check them from the batch header (Scalars, the common case)."""
    if meta.problem is not None:
        raise invalid(msg, meta.entity_path, meta.problem)
    if meta.reads_values and not meta.values_checked:
        validated_batch(msg, meta)


def validated_batch(msg: ArrowMessage, meta: ChunkMeta | None = None) -> pa.RecordBatch:
    """The chunk as a record batch, once it is known that every value in it can be read safely;
    else InvalidChunkError naming the chunk, its entity and its byte offset."""
    entity_path = meta.entity_path if meta is not None else None
    try:
        batch = read_chunk(msg)
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
        component = metadata.get(b"rerun:component", fld.name.encode()).decode()
        problem = conformance.component_type_problem(component, fld.name, fld.type)
        if problem is not None:
            return problem
        if not fld.nullable and batch.column(i).null_count:
            return f"column {fld.name!r} is declared non-nullable but holds nulls"
    return None
