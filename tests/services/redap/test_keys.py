"""Chunk keys: each the bytes protobuf writes for Rerun's `ChunkKey`, however many are written at
once and whatever the sizes of their numbers; keys that are not ours are refused."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from services.redap.keys import ChunkLocation, chunk_key, key_column, parse_chunk_key
from services.redap.pb import cloud_pb2
from services.rrd.pb import common_pb2


def protobuf_key(segment_id: str, offset: int, length: int, chunk_id: bytes) -> bytes:
    return cloud_pb2.ChunkKey(
        chunk_id=common_pb2.Tuid(time_ns=int.from_bytes(chunk_id[:8], "big"), inc=int.from_bytes(chunk_id[8:], "big")),
        data_source_kind=cloud_pb2.DATA_SOURCE_KIND_RRD,
        location=cloud_pb2.RrdChunkLocation(
            url=f"fleet:{segment_id}", offset=offset, length=length
        ).SerializeToString(),
    ).SerializeToString()


@pytest.mark.parametrize(
    ("run_id", "offset", "length", "chunk_id"),
    [
        ("rec-points", 12, 933, bytes(range(16))),
        ("r", 0, 17, bytes(16)),
        ("a" * 128, 2**40 + 3, 2**33 + 1, b"\xff" * 16),
        ("robot-7_2026.run-1", 127, 128, b"\x18\xea\x87" + bytes(13)),
        ("nav-1~3", 2**64 - 1, 2**63, b"\x01" * 16),
    ],
)
def test_a_key_is_the_chunk_key_message_protobuf_writes(run_id: str, offset: int, length: int, chunk_id: bytes):
    key = chunk_key(run_id, offset, length, chunk_id)
    assert key == protobuf_key(run_id, offset, length, chunk_id)
    segment, _, _ = run_id.partition("~")
    assert parse_chunk_key(key) == ChunkLocation(segment, offset, length, chunk_id, run_id if "~" in run_id else "")


@pytest.mark.parametrize("segment_id", ["r", "robot-7_2026.run-1", "x" * 200, "nav-1~12"])
def test_a_column_of_keys_is_each_key_protobuf_writes(segment_id: str):
    # Numbers of every varint length (1 to 10 bytes) at every row, so that rows of different
    # lengths sit side by side, and a location long enough for a two-byte length prefix.
    rng = np.random.default_rng(5)
    count = 400
    offsets = [int(v) for v in (rng.integers(0, 2**63, count) >> rng.integers(0, 63, count))]
    lengths = [int(v) for v in (rng.integers(0, 2**63, count) >> rng.integers(0, 63, count))]
    offsets[:3], lengths[:3] = [0, 2**64 - 1, 127], [128, 1, 2**64 - 1]
    ids = [rng.bytes(16) for _ in range(count)]
    expected = [protobuf_key(segment_id, o, n, i) for o, n, i in zip(offsets, lengths, ids, strict=True)]
    for given in (ids, pa.array(ids, pa.binary(16)), pa.chunked_array([pa.array(ids, pa.binary(16))])):
        column = key_column(segment_id, offsets, lengths, given)
        assert column.type == pa.binary()
        assert column.to_pylist() == expected


def test_a_column_of_a_sliced_id_array_reads_the_slice():
    ids = [bytes([n]) * 16 for n in range(10)]
    sliced = pa.array(ids, pa.binary(16)).slice(3, 4)
    column = key_column("run", [1, 2, 3, 4], [20, 30, 40, 50], sliced)
    assert [parse_chunk_key(k).chunk_id for k in column.to_pylist()] == ids[3:7]


def test_no_chunks_make_an_empty_column():
    assert key_column("run", [], [], []).to_pylist() == []


@pytest.mark.parametrize(
    "key",
    [
        b"",
        b"\xff\xfe not protobuf",
        cloud_pb2.ChunkKey(
            location=cloud_pb2.RrdChunkLocation(url="s3://bucket/x.rrd", offset=0, length=100).SerializeToString()
        ).SerializeToString(),
        cloud_pb2.ChunkKey(
            location=cloud_pb2.RrdChunkLocation(url="fleet:run", offset=0, length=10).SerializeToString()
        ).SerializeToString(),
        bytes(32),  # what Rerun's own server hands out: 32 opaque bytes
    ],
)
def test_keys_that_are_not_ours_are_refused(key: bytes):
    with pytest.raises(Exception) as info:
        parse_chunk_key(key)
    assert getattr(info.value, "grpc_status", lambda: "")() == "INVALID_ARGUMENT"
