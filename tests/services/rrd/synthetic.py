"""Small recordings built in the test process, without the Rerun SDK: a stream header, the
SetStoreInfo an SDK sends (twice, as it does), chunks of Scalars on a few entities with a `frame`
sequence timeline (and one static chunk), then End. Each chunk has an id of its own and a size that
grows with its index, so a run written from one is a file of messages of many sizes. For tests of
the fast lane that need whole, valid recordings but not what the SDK itself writes."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import lz4.block
import pyarrow as pa

from services.rrd.frames import MessageKind, RerunVersion, StreamHeader
from services.rrd.messages import Event, tuid_proto
from services.rrd.pb import common_pb2, log_msg_pb2

VERSION = RerunVersion(0, 24, 0)
APPLICATION = "fleet_synthetic"
ENTITIES = ("/robot/speed", "/robot/battery", "/arm/torque")


def chunk_id(recording_id: str, index: int) -> bytes:
    """A 16-byte chunk id, distinct per recording and index (ids of different recordings never meet)."""
    prefix = (recording_id.encode() * 8)[:8]
    return prefix + index.to_bytes(8, "big")


def _store_id(recording_id: str) -> common_pb2.StoreId:
    return common_pb2.StoreId(
        kind=common_pb2.STORE_KIND_RECORDING,
        recording_id=recording_id,
        application_id=common_pb2.ApplicationId(id=APPLICATION),
    )


def store_info_body(recording_id: str) -> bytes:
    bits = int.from_bytes(VERSION.to_bytes(), "little")
    info = log_msg_pb2.StoreInfo(
        store_id=_store_id(recording_id), store_version=log_msg_pb2.StoreVersion(crate_version_bits=bits)
    )
    return log_msg_pb2.SetStoreInfo(row_id=common_pb2.Tuid(time_ns=1, inc=1), info=info).SerializeToString()


def chunk_ipc(entity: str, id_: bytes, frames: list[int] | None, values: list[list[float]]) -> bytes:
    """A Rerun chunk (RowId, a `frame` index unless static, Scalars) as an Arrow IPC stream."""
    fields = [pa.field("rerun.controls.RowId", pa.binary(16), metadata={b"rerun:kind": b"control"})]
    columns: list[pa.Array] = [pa.array([id_[:8] + i.to_bytes(8, "big") for i in range(len(values))], pa.binary(16))]
    if frames is not None:
        fields.append(pa.field("frame", pa.int64(), metadata={b"rerun:kind": b"index", b"rerun:index_name": b"frame"}))
        columns.append(pa.array(frames, pa.int64()))
    fields.append(
        pa.field(
            "Scalars:scalars",
            pa.list_(pa.float64()),
            metadata={
                b"rerun:kind": b"data",
                b"rerun:component": b"Scalars:scalars",
                b"rerun:archetype": b"rerun.archetypes.Scalars",
            },
        )
    )
    columns.append(pa.array(values, pa.list_(pa.float64())))
    metadata = {
        b"sorbet:version": b"0.1.3",
        b"rerun:entity_path": entity.encode(),
        b"rerun:id": b"chunk_" + id_.hex().encode(),
    }
    schema = pa.schema(fields, metadata=metadata)
    sink = io.BytesIO()
    with pa.ipc.new_stream(sink, schema) as writer:
        writer.write_batch(pa.record_batch(columns, schema=schema))
    return sink.getvalue()


def arrow_body(recording_id: str, id_: bytes, ipc: bytes, *, static: bool) -> bytes:
    return log_msg_pb2.ArrowMsg(
        store_id=_store_id(recording_id),
        chunk_id=tuid_proto(id_),
        is_static=static,
        compression=common_pb2.COMPRESSION_LZ4,
        uncompressed_size=len(ipc),
        encoding=log_msg_pb2.ENCODING_ARROW_IPC,
        payload=lz4.block.compress(ipc, store_size=False),
    ).SerializeToString()


def _frame(kind: MessageKind, body: bytes) -> bytes:
    return struct.pack("<QQ", kind, len(body)) + body


def recording_bytes(recording_id: str, chunks: int = 12) -> bytes:
    """A whole recording: header, two SetStoreInfo, one static chunk, then `chunks - 1` temporal
    chunks round-robin over ENTITIES (chunk i holds i + 1 rows), then End."""
    parts = [StreamHeader(VERSION).encode()]
    info = _frame(MessageKind.SET_STORE_INFO, store_info_body(recording_id))
    parts += [info, info]
    for i in range(chunks):
        id_ = chunk_id(recording_id, i)
        static = i == 0
        rows = 1 if static else i + 1
        frames = None if static else list(range(i * 100, i * 100 + rows))
        values = [[float(i), float(r)] for r in range(rows)]
        ipc = chunk_ipc(ENTITIES[i % len(ENTITIES)], id_, frames, values)
        parts.append(_frame(MessageKind.ARROW_MSG, arrow_body(recording_id, id_, ipc, static=static)))
    parts.append(_frame(MessageKind.END, b""))
    return b"".join(parts)


def write_recording(path: Path, recording_id: str, chunks: int = 12) -> Path:
    path.write_bytes(recording_bytes(recording_id, chunks))
    return path


def recording_events(path: Path) -> list[Event]:
    from services.rrd import iter_events

    return list(iter_events(path))
