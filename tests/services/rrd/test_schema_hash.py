"""Rerun's hash of a Sorbet schema: the footers the SDK writes carry it, and Rust's Arrow writer
(here through DataFusion, which writes Arrow IPC with it) lays out the bytes it is taken of."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pyarrow as pa
import pytest

from services.rrd.footer import read_footer
from services.rrd.manifest import read_sorbet_schema, schema_sha256
from services.rrd.schema_hash import rust_schema_message, sorbet_schema_sha256
from tests.services.rrd.recordings import FOOTER_FILES, Recording


@pytest.mark.sdk
@pytest.mark.parametrize("name", FOOTER_FILES)
def test_the_hash_is_the_one_rerun_writes_in_its_footers(recordings: dict[str, Recording], name: str):
    with open(recordings[name].path, "rb") as fh:
        footer = read_footer(fh)
    assert footer is not None and footer.manifests
    for manifest in footer.manifests:  # recordings and blueprints (unions, structs, lists of all kinds)
        schema = read_sorbet_schema(manifest)
        assert rust_schema_message(pa.schema(sorted(schema, key=lambda f: f.name))) is not None
        assert sorbet_schema_sha256(schema) == manifest.sorbet_schema_sha256
        assert schema_sha256(schema) == manifest.sorbet_schema_sha256  # what our footers now carry


MD = {b"rerun:kind": b"data", b"rerun:component": b"Points3D:positions", b"a": b"1"}
SCHEMAS = {
    "scalars": pa.schema(
        [
            pa.field("u8", pa.uint8()),
            pa.field("i16", pa.int16(), nullable=False),
            pa.field("u32", pa.uint32()),
            pa.field("i64", pa.int64(), metadata={b"rerun:kind": b"index"}),
            pa.field("f16", pa.float16()),
            pa.field("f32", pa.float32()),
            pa.field("f64", pa.float64(), nullable=False),
            pa.field("b", pa.bool_()),
            pa.field("s", pa.string()),
            pa.field("bin", pa.binary()),
            pa.field("lbin", pa.large_binary()),
            pa.field("ls", pa.large_string()),
            pa.field("fsb", pa.binary(16), nullable=False, metadata=MD),
        ]
    ),
    "time": pa.schema(
        [
            pa.field("ts", pa.timestamp("ns")),
            pa.field("ts_utc", pa.timestamp("us", tz="UTC")),
            pa.field("ts_s", pa.timestamp("s", tz="+01:00")),
            pa.field("dur_ns", pa.duration("ns")),
            pa.field("dur_ms", pa.duration("ms")),
            pa.field("d32", pa.date32()),
            pa.field("d64", pa.date64()),
            pa.field("t32", pa.time32("ms")),
            pa.field("t64", pa.time64("ns")),
        ]
    ),
    "nested": pa.schema(
        [
            pa.field("positions", pa.list_(pa.list_(pa.float32(), 3)), metadata=MD),
            pa.field("llist", pa.large_list(pa.int32())),
            pa.field(
                "struct",
                pa.struct([pa.field("x", pa.float32(), nullable=False), pa.field("name", pa.string(), metadata=MD)]),
            ),
            pa.field(
                "dense",
                pa.dense_union([pa.field("_null_markers", pa.null()), pa.field("v", pa.list_(pa.float64()))]),
            ),
            pa.field("sparse", pa.sparse_union([pa.field("a", pa.int8()), pa.field("b", pa.bool_())], [3, 7])),
            pa.field("map", pa.map_(pa.string(), pa.int64())),
            pa.field("null", pa.null()),
        ],
        metadata={b"sorbet:version": b"0.1.4"},
    ),
}


def empty(t: pa.DataType) -> pa.Array:
    """An empty array of any type (pyarrow makes no empty union from a list)."""
    if pa.types.is_union(t):
        children = [empty(t.field(i).type) for i in range(t.num_fields)]
        names, codes = [t.field(i).name for i in range(t.num_fields)], list(t.type_codes)
        types = pa.array([], pa.int8())
        if t.mode == "dense":
            return pa.UnionArray.from_dense(types, pa.array([], pa.int32()), children, names, codes)
        return pa.UnionArray.from_sparse(types, children, names, codes)
    return pa.array([], type=t)


def empty_batch(schema: pa.Schema) -> pa.RecordBatch:
    return pa.RecordBatch.from_arrays([empty(f.type) for f in schema], schema=schema)


@pytest.mark.parametrize("name", sorted(SCHEMAS))
def test_the_schema_message_is_the_one_rusts_arrow_writes(name: str, tmp_path: Path):
    datafusion = pytest.importorskip("datafusion")  # Rust's Arrow, writing an IPC file
    schema = SCHEMAS[name]
    context = datafusion.SessionContext()
    context.register_record_batches("t", [[empty_batch(schema)]])
    out = tmp_path / "out.arrow"
    context.sql(f"COPY t TO '{out}' STORED AS ARROW").collect()
    written = out.read_bytes()
    start = written.index(b"\xff\xff\xff\xff")  # after the file magic and its padding: the schema message
    length = int.from_bytes(written[start + 4 : start + 8], "little")
    rust = written[start : start + 8 + length]
    assert pa.ipc.open_file(str(out)).schema.equals(schema, check_metadata=True)
    assert rust_schema_message(schema) == rust
    ordered = pa.schema(sorted(schema, key=lambda f: f.name))
    if ordered != schema or schema.metadata:
        context.register_record_batches("o", [[empty_batch(ordered)]])
        out_sorted = tmp_path / "sorted.arrow"
        context.sql(f"COPY o TO '{out_sorted}' STORED AS ARROW").collect()
        data = out_sorted.read_bytes()
        begin = data.index(b"\xff\xff\xff\xff")
        message = data[begin : begin + 8 + int.from_bytes(data[begin + 4 : begin + 8], "little")]
        assert sorbet_schema_sha256(schema) == hashlib.sha256(message).digest()
