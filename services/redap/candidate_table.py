"""The tables of chunk candidates that FindChunks and QueryDataset answer, column for column as
Rerun's servers answer them (names, types, nullability and `rerun:kind` metadata, checked against
`rerun server` 0.41): one row per chunk, and for each the key FetchChunks takes back.

`chunk_byte_len` is the chunk's bytes as stored (its ArrowMsg, what the RRD manifest calls
`chunk_byte_size`), `chunk_byte_size_uncompressed` its Arrow payload once decompressed (null when
not known). The direct URL columns are null (clients fetch the chunks with FetchChunks) unless a
segment's rows are read from the bucket (`direct.py`): then each row names its recording's presigned
URL and when it expires, dictionary-encoded (one value per segment). A snapshot episode's rows
(`RUN~N`) name each chunk by an id of the episode's own (`chunks.episode_chunk_id`), their keys the
chunk itself."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence

import pyarrow as pa

from services.redap.direct import DirectUrl
from services.redap.keys import EPISODE_SEPARATOR, episode_chunk_id, key_column
from services.rrd.frames import MESSAGE_HEADER_SIZE
from services.sealed.index import IndexRow

LAYER = "base"  # a run is one layer, named as Rerun names a segment's first
PART_ROWS = 8192  # rows per streamed part: parts stay around a megabyte

_CONTROL = {b"rerun:kind": b"control"}
FIELDS = (
    pa.field("chunk_id", pa.binary(16), nullable=False, metadata=_CONTROL),
    pa.field("chunk_segment_id", pa.utf8(), nullable=False, metadata=_CONTROL),
    pa.field("rerun_segment_layer", pa.utf8(), nullable=False),
    pa.field("chunk_key", pa.binary(), nullable=False),
    pa.field("chunk_entity_path", pa.utf8(), nullable=False, metadata=_CONTROL),
    pa.field("chunk_is_static", pa.bool_(), nullable=False, metadata=_CONTROL),
    pa.field("chunk_byte_len", pa.uint64(), nullable=False),
    pa.field("chunk_byte_size_uncompressed", pa.uint64()),
)
TIMELINE_START = pa.field("chunk_timeline_start", pa.int64(), metadata={b"rerun:kind": b"index"})
DIRECT_URL_FIELDS = (
    pa.field("rerun_layer_direct_url", pa.dictionary(pa.int32(), pa.utf8())),
    pa.field("rerun_layer_direct_url_expires_at", pa.dictionary(pa.int32(), pa.int64())),
)


def start_column(timeline: str) -> pa.Field:
    """QueryDataset's `{timeline}:start`: each chunk's first time on it (null for static chunks)."""
    metadata = {b"rerun:index": timeline.encode(), b"rerun:index_marker": b"start", b"rerun:kind": b"index"}
    return pa.field(f"{timeline}:start", pa.int64(), metadata=metadata)


def find_chunks_schema() -> pa.Schema:
    """FindChunks' fixed layout: the timeline start sits before the direct URLs."""
    return pa.schema([*FIELDS, TIMELINE_START, *DIRECT_URL_FIELDS])


def query_dataset_schema(timeline: str | None) -> pa.Schema:
    """QueryDataset's: the direct URLs, then `{timeline}:start` when a timeline was named."""
    return pa.schema([*FIELDS, *DIRECT_URL_FIELDS, *([start_column(timeline)] if timeline else [])])


def _timeline_start(row: IndexRow, timeline: str | None) -> int | None:
    if timeline is None:
        return None
    return next((t.min for t in row.timelines if t.name == timeline), None)


def _null_dictionary(field: pa.Field, length: int) -> pa.Array:
    return pa.DictionaryArray.from_arrays(pa.nulls(length, pa.int32()), pa.array([], field.type.value_type))


def _direct_columns(direct: DirectUrl | None, length: int) -> dict[str, pa.Array]:
    if direct is None:
        return {field.name: _null_dictionary(field, length) for field in DIRECT_URL_FIELDS}
    same = pa.array([0] * length, pa.int32())  # every row: the one recording's URL
    return {
        "rerun_layer_direct_url": pa.DictionaryArray.from_arrays(same, pa.array([direct.url], pa.utf8())),
        "rerun_layer_direct_url_expires_at": pa.DictionaryArray.from_arrays(
            same, pa.array([direct.expires_at_ns], pa.int64())
        ),
    }


def candidate_batch(
    schema: pa.Schema,
    segment_id: str,
    rows: Sequence[IndexRow],
    uncompressed: Mapping[bytes, int],
    timeline: str | None,
    direct: DirectUrl | None = None,
) -> pa.RecordBatch:
    """The rows of one segment's candidate chunks in `schema` (one of the two layouts above), keyed
    for that segment (a run, or a snapshot's episode of one); the timeline start column, whichever
    its name, holds each chunk's first time on `timeline`; `direct`: the URL its rows are read from."""
    ids = [r.chunk_id or b"" for r in rows]
    shown = [episode_chunk_id(segment_id, i) for i in ids] if EPISODE_SEPARATOR in segment_id else ids
    columns: dict[str, pa.Array] = {
        "chunk_id": pa.array(shown, pa.binary(16)),
        "chunk_segment_id": pa.array([segment_id] * len(rows), pa.utf8()),
        "rerun_segment_layer": pa.array([LAYER] * len(rows), pa.utf8()),
        "chunk_key": key_column(segment_id, [r.offset for r in rows], [r.length for r in rows], ids),
        "chunk_entity_path": pa.array([r.entity_path or "/" for r in rows], pa.utf8()),
        "chunk_is_static": pa.array([r.is_static for r in rows], pa.bool_()),
        "chunk_byte_len": pa.array([r.length - MESSAGE_HEADER_SIZE for r in rows], pa.uint64()),
        "chunk_byte_size_uncompressed": pa.array([uncompressed.get(i) for i in ids], pa.uint64()),
        **_direct_columns(direct, len(rows)),
    }
    starts = pa.array([_timeline_start(r, timeline) for r in rows], pa.int64())
    arrays = []
    for field in schema:
        arrays.append(columns.get(field.name, starts))
    return pa.RecordBatch.from_arrays(arrays, schema=schema)


def candidate_batches(
    schema: pa.Schema,
    segment_id: str,
    rows: Sequence[IndexRow],
    uncompressed: Mapping[bytes, int],
    timeline: str | None,
    direct: DirectUrl | None = None,
) -> Iterator[pa.RecordBatch]:
    """`candidate_batch` in parts of at most PART_ROWS rows."""
    for start in range(0, len(rows), PART_ROWS):
        yield candidate_batch(schema, segment_id, rows[start : start + PART_ROWS], uncompressed, timeline, direct)
