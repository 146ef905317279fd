"""The per-chunk value checks read from a record batch's body (`value_checks`) against pyarrow's
full validation, on chunks of many Arrow types whose offsets and string bytes are damaged.

Ingest's verdict on a chunk (`check_chunk`) must be pyarrow's full validation's, whichever way it
was reached: from the body (the common, cheap way) or by asking pyarrow. A chunk that passes is
read whole (`to_pylist`), which must never crash."""

from __future__ import annotations

import struct
from collections.abc import Iterator

import lz4.block
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from services.rrd import errors
from services.rrd.chunk import chunk_meta
from services.rrd.decoder import decode_message
from services.rrd.messages import ArrowMessage
from services.rrd.pb import common_pb2, log_msg_pb2
from services.rrd.validate import check_chunk

ROW_ID = pa.field("rerun.controls.RowId", pa.binary(16), nullable=False, metadata={b"rerun:kind": b"control"})
FRAME = pa.field("frame", pa.int64(), metadata={b"rerun:kind": b"index", b"rerun:index_name": b"frame"})

# Column types of components the depot does not read (Points3D, Image, AnyValues, ...): each with
# values for `rows` rows, some of them several values long.
TYPES: dict[str, tuple[pa.DataType, object]] = {
    "positions": (pa.list_(pa.list_(pa.float32(), 3)), [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]),
    "colors": (pa.list_(pa.uint32()), [1, 2, 3]),
    "labels": (pa.list_(pa.string()), ["a", "ßé", "", "日本"]),
    "blob": (pa.list_(pa.list_(pa.uint8())), [[1, 2, 3], [], [4]]),
    "bytes": (pa.list_(pa.binary()), [b"\x00\xff", b"", b"abc"]),
    "nested": (pa.list_(pa.struct([("name", pa.string()), ("w", pa.float32())])), [{"name": "x", "w": 1.0}]),
    "map": (pa.list_(pa.map_(pa.string(), pa.int32())), [[("k", 1), ("kk", 2)]]),
    "large": (pa.large_list(pa.large_string()), ["long", "é"]),
    "flat_text": (pa.string(), "plain"),
    "flags": (pa.list_(pa.bool_()), [True, False, True]),
}


def chunk_message(columns: list[str], rows: int, compress: bool) -> ArrowMessage:
    fields = [ROW_ID, FRAME]
    arrays: list[pa.Array] = [
        pa.array([bytes(8) + i.to_bytes(8, "big") for i in range(rows)], pa.binary(16)),
        pa.array(range(rows), pa.int64()),
    ]
    for name in columns:
        kind, value = TYPES[name]
        fields.append(pa.field(f"Custom:{name}", kind, metadata={b"rerun:kind": b"data", b"rerun:component": name}))
        arrays.append(pa.array([value] * rows, kind))
    schema = pa.schema(fields, metadata={b"rerun:entity_path": b"/custom", b"rerun:id": b"chunk_" + b"0" * 31 + b"7"})
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, schema) as writer:
        writer.write_batch(pa.record_batch(arrays, schema=schema))
    return arrow_message(sink.getvalue().to_pybytes(), compress)


def arrow_message(ipc: bytes, compress: bool) -> ArrowMessage:
    pb = log_msg_pb2.ArrowMsg(
        store_id=common_pb2.StoreId(kind=common_pb2.STORE_KIND_RECORDING, recording_id="r"),
        compression=common_pb2.COMPRESSION_LZ4 if compress else common_pb2.COMPRESSION_NONE,
        uncompressed_size=len(ipc),
        encoding=log_msg_pb2.ENCODING_ARROW_IPC,
        payload=lz4.block.compress(ipc, store_size=False) if compress else ipc,
    )
    msg = decode_message(2, pb.SerializeToString())
    assert isinstance(msg, ArrowMessage)
    return msg


def ipc_of(msg: ArrowMessage) -> bytes:
    return (
        lz4.block.decompress(msg.payload, uncompressed_size=msg.uncompressed_size)
        if msg.compression == 2
        else bytes(msg.payload)
    )


def damageable(ipc: bytes) -> list[tuple[int, int, int]]:
    """(position, size, width) of every offsets buffer and every string's bytes in the IPC stream,
    width 4 or 8 for offsets, 1 for bytes."""
    buffer = pa.py_buffer(ipc)
    reader = pa.BufferReader(buffer)
    schema = pa.ipc.read_schema(pa.ipc.read_message(reader))
    batch = pa.ipc.read_record_batch(pa.ipc.read_message(reader), schema)
    spots = []
    for column in batch.columns:
        for array in _arrays(column):
            kind = array.type
            large = pa.types.is_large_list(kind) or pa.types.is_large_string(kind) or pa.types.is_large_binary(kind)
            if pa.types.is_list(kind) or pa.types.is_large_list(kind) or pa.types.is_map(kind):
                offsets = array.buffers()[1]
                spots.append((offsets.address - buffer.address, offsets.size, 8 if large else 4))
            elif pa.types.is_string(kind) or pa.types.is_large_string(kind) or pa.types.is_binary(kind):
                offsets, data = array.buffers()[1], array.buffers()[2]
                spots.append((offsets.address - buffer.address, offsets.size, 8 if large else 4))
                if data is not None and data.size and pa.types.is_string(kind):
                    spots.append((data.address - buffer.address, data.size, 1))
    return spots


def _arrays(array: pa.Array) -> Iterator[pa.Array]:
    yield array
    kind = array.type
    if pa.types.is_list(kind) or pa.types.is_large_list(kind) or pa.types.is_fixed_size_list(kind):
        yield from _arrays(array.values)
    elif pa.types.is_map(kind):
        yield from _arrays(array.keys)
        yield from _arrays(array.items)
    elif pa.types.is_struct(kind):
        for i in range(kind.num_fields):
            yield from _arrays(array.field(i))


def pyarrow_verdict(ipc: bytes) -> bool:
    """Whether pyarrow reads the chunk and its full validation passes."""
    try:
        reader = pa.BufferReader(pa.py_buffer(ipc))
        schema = pa.ipc.read_schema(pa.ipc.read_message(reader))
        batch = pa.ipc.read_record_batch(pa.ipc.read_message(reader), schema)
        batch.validate(full=True)
    except (pa.ArrowException, ValueError, OSError):
        return False
    return True


def ingest_verdict(msg: ArrowMessage) -> bool:
    try:
        check_chunk(msg, chunk_meta(msg))
    except errors.RrdError:
        return False
    return True


INTERESTING = [0, 1, 2, 3, 5, -1, 7, 1 << 20, 0x7FFFFFF0, -(1 << 31)]
TEXT_DAMAGE = [b"\xff", b"\x80", b"\xc3", b"\xe6\x97", b"\xed\xa0\x80"]  # invalid, lone continuation, cut, surrogate


@pytest.mark.parametrize("name", sorted(TYPES))
@pytest.mark.parametrize("rows", [1, 3])
def test_intact_chunks_are_checked_from_their_body(name: str, rows: int) -> None:
    msg = chunk_message([name], rows, compress=True)
    meta = chunk_meta(msg)
    assert meta.values_checked, f"{name}: an intact chunk should not need pyarrow"
    check_chunk(msg, meta)


@settings(
    max_examples=300, deadline=None, derandomize=True, database=None, suppress_health_check=[HealthCheck.too_slow]
)
@given(
    columns=st.lists(st.sampled_from(sorted(TYPES)), min_size=1, max_size=3, unique=True),
    rows=st.sampled_from([1, 2, 4]),
    compress=st.booleans(),
    data=st.data(),
)
def test_damaged_values_get_pyarrows_verdict(
    columns: list[str], rows: int, compress: bool, data: st.DataObject
) -> None:
    ipc = bytearray(ipc_of(chunk_message(columns, rows, compress=False)))
    for _ in range(data.draw(st.integers(1, 3))):
        at, size, width = data.draw(st.sampled_from(damageable(bytes(ipc))))
        if width == 1:
            damage = data.draw(st.sampled_from(TEXT_DAMAGE))
            slot = data.draw(st.integers(0, max(0, size - len(damage))))
            ipc[at + slot : at + slot + len(damage)] = damage[: size - slot]
        else:
            slot = data.draw(st.integers(0, size // width - 1))
            value = data.draw(st.sampled_from(INTERESTING))
            ipc[at + width * slot : at + width * (slot + 1)] = struct.pack("<q" if width == 8 else "<i", value)
    msg = arrow_message(bytes(ipc), compress)
    expected = pyarrow_verdict(bytes(ipc))
    assert ingest_verdict(msg) == expected
    if expected:
        pa.ipc.open_stream(bytes(ipc)).read_all().to_pylist()  # every value reads


def test_a_string_value_starting_inside_a_character_is_refused() -> None:
    """Two values "ß" split as b"\\xc3" and b"\\x9f": their bytes together are UTF-8, each alone is not."""
    msg = chunk_message(["labels"], 1, compress=False)
    ipc = bytearray(ipc_of(msg))
    offsets_at, _, _ = damageable(bytes(ipc))[1]  # the strings' own offsets
    assert struct.unpack_from("<5i", ipc, offsets_at) == (0, 1, 5, 5, 11)
    struct.pack_into("<i", ipc, offsets_at + 8, 2)  # "ßé" now ends after the first byte of "ß"
    assert not pyarrow_verdict(bytes(ipc))
    assert not ingest_verdict(arrow_message(bytes(ipc), compress=True))
