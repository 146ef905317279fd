"""Hostile Arrow IPC and LZ4, as an attacker with any token would send them: chunks for the ingest
paths (gRPC streams, uploads, relays between nodes) and tables for the catalog service's
dataframe parts. Each case is damaged in one way that a reader trusting the data would pay for: an
offset pointing far past its data (read: out of bounds, a crash), an LZ4 block declaring far more
than it holds (decompressed: gigabytes), buffers compressed inside the IPC stream (pyarrow would
allocate what they declare), bytes that are no LZ4 block or no IPC stream."""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass

import lz4.block
import pyarrow as pa

from services.rrd.pb import common_pb2, log_msg_pb2

ROW_ID = pa.field("rerun.controls.RowId", pa.binary(16), nullable=False, metadata={b"rerun:kind": b"control"})
FRAME = pa.field("frame", pa.int64(), metadata={b"rerun:kind": b"index", b"rerun:index_name": b"frame"})
POSITIONS = pa.list_(pa.list_(pa.float32(), 3))
FAR = 0x7FFFFFF0  # the offset of the finding: 2 GiB past any data
GIB = 1 << 30


def ipc_stream(batch: pa.RecordBatch, options: pa.ipc.IpcWriteOptions | None = None) -> bytes:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema, options=options) as writer:
        writer.write_batch(batch)
    return bytes(sink.getvalue().to_pybytes())


def chunk_batch(
    entity: str, columns: Sequence[tuple[str, pa.DataType, object]], rows: int = 3, chunk: int = 7
) -> pa.RecordBatch:
    """A Rerun chunk of `rows` rows on a `frame` timeline: `columns` are (component, type, value of
    each row)."""
    fields = [ROW_ID, FRAME]
    arrays: list[pa.Array] = [
        pa.array([chunk.to_bytes(8, "big") + i.to_bytes(8, "big") for i in range(rows)], pa.binary(16)),
        pa.array(range(rows), pa.int64()),
    ]
    for component, kind, value in columns:
        metadata = {b"rerun:kind": b"data", b"rerun:component": component.encode()}
        fields.append(pa.field(component, kind, metadata=metadata))
        arrays.append(pa.array([value] * rows, kind))
    metadata = {b"rerun:entity_path": entity.encode(), b"rerun:id": f"chunk_{chunk:032x}".encode()}
    schema = pa.schema(fields, metadata=metadata)
    return pa.record_batch(arrays, schema=schema)


def points(chunk: int = 7) -> pa.RecordBatch:
    """Points3D-like positions: a component the depot never reads (so only full validation sees it)."""
    return chunk_batch("/world/points", [("Points3D:positions", POSITIONS, [[1.0, 2.0, 3.0]])], chunk=chunk)


def with_offset(ipc: bytes, intact: tuple[int, ...], slot: int, value: int) -> bytes:
    """`ipc` with the int32 offsets `intact` found in it and the one at `slot` set to `value`."""
    packed = struct.pack(f"<{len(intact)}i", *intact)
    at = ipc.index(packed)
    return ipc[: at + 4 * slot] + struct.pack("<i", value) + ipc[at + 4 * slot + 4 :]


def far_offset_points(chunk: int = 7) -> bytes:
    """The positions' list offsets 0, 1, 2, 3 with the middle one 2 GiB past the values."""
    return with_offset(ipc_stream(points(chunk)), (0, 1, 2, 3), 1, FAR)


def body_compressed(batch: pa.RecordBatch) -> bytes:
    """An IPC stream whose record batch compresses its buffers (LZ4 frames), each declaring 1 GiB."""
    ipc = bytearray(ipc_stream(batch, pa.ipc.IpcWriteOptions(compression="lz4")))
    magic = b"\x04\x22\x4d\x18"  # an LZ4 frame: the buffer's int64 uncompressed length precedes it
    at = ipc.find(magic)
    while at >= 8:
        ipc[at - 8 : at] = struct.pack("<q", GIB)
        at = ipc.find(magic, at + 4)
    return bytes(ipc)


@dataclass(frozen=True)
class Payload:
    """What a message carries: its bytes, LZ4 or not, and the size it declares once decompressed."""

    name: str
    payload: bytes
    lz4: bool
    declared: int


def lz4_payload(name: str, ipc: bytes) -> Payload:
    return Payload(name, lz4.block.compress(ipc, store_size=False), True, len(ipc))


def hostile_payloads(ipc: bytes, damaged_ipc: bytes, body_compressed_ipc: bytes) -> list[Payload]:
    """The ways one IPC stream (and a damaged copy of it) is sent hostile."""
    zeros = lz4.block.compress(bytes(4 << 20), store_size=False)  # 4 MiB of zeros: ~16 KB of LZ4
    return [
        lz4_payload("far offset, LZ4", damaged_ipc),
        Payload("far offset, uncompressed", damaged_ipc, False, len(damaged_ipc)),
        Payload("LZ4 declaring 1 GiB", zeros, True, GIB),
        Payload("LZ4 declaring less than it holds", lz4.block.compress(ipc, store_size=False), True, len(ipc) // 2),
        Payload("bytes that are no LZ4 block", bytes(range(256)) * 4, True, 4096),
        Payload("bytes that are no IPC stream", b"\xff\xff\xff\xff" + bytes(60), False, 64),
        lz4_payload("IPC body compression declaring 1 GiB", body_compressed_ipc),
    ]


def hostile_chunks() -> list[Payload]:
    """Chunk payloads for the ingest paths."""
    return hostile_payloads(ipc_stream(points()), far_offset_points(), body_compressed(points()))


def arrow_msg(recording_id: str, payload: Payload, chunk: int = 7) -> bytes:
    """An ArrowMsg carrying `payload` in `recording_id`'s store."""
    return log_msg_pb2.ArrowMsg(
        store_id=common_pb2.StoreId(
            kind=common_pb2.STORE_KIND_RECORDING,
            recording_id=recording_id,
            application_id=common_pb2.ApplicationId(id="hostile"),
        ),
        chunk_id=common_pb2.Tuid(time_ns=chunk, inc=0),
        compression=common_pb2.COMPRESSION_LZ4 if payload.lz4 else common_pb2.COMPRESSION_NONE,
        uncompressed_size=payload.declared,
        encoding=log_msg_pb2.ENCODING_ARROW_IPC,
        payload=payload.payload,
    ).SerializeToString()


def chunk_key_table(keys: pa.Array) -> pa.RecordBatch:
    return pa.record_batch([keys], names=["chunk_key"])


def hostile_dataframe_parts() -> list[common_pb2.DataframePart]:
    """Dataframe parts for FetchChunks' chunk list (`chunk_key`, binary), each hostile."""
    keys = pa.array([b"a" * 10, b"b" * 10, b"c" * 10], pa.binary())
    ipc = ipc_stream(chunk_key_table(keys))
    far = struct.pack("<4i", 0, 10, 20, 30)
    at = ipc.index(far)
    damaged = ipc[:at] + struct.pack("<4i", 0, FAR, 20, 30) + ipc[at + 16 :]
    parts = [_part(p) for p in hostile_payloads(ipc, damaged, body_compressed(chunk_key_table(keys)))]
    # A column that is no binary: 2^31 - 1 nulls (no buffer bounds their count: a list of them would
    # take 16 GiB), and text.
    nulls = pa.Array.from_buffers(pa.null(), (1 << 31) - 1, [None], null_count=(1 << 31) - 1)
    parts.append(_part(lz4_payload("nulls", ipc_stream(chunk_key_table(nulls)))))
    parts.append(_part(lz4_payload("text", ipc_stream(chunk_key_table(pa.array(["x", "y"]))))))
    return parts


def _part(payload: Payload) -> common_pb2.DataframePart:
    return common_pb2.DataframePart(
        encoder_version=common_pb2.ENCODER_VERSION_V0,
        payload=payload.payload,
        compression=common_pb2.COMPRESSION_LZ4 if payload.lz4 else common_pb2.COMPRESSION_NONE,
        uncompressed_size=payload.declared,
    )
