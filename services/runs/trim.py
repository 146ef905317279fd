"""`exact=true`: a chunk that straddles the time window is cut to the rows inside it.

The only place a payload is re-encoded: the kept rows become a new chunk with a new chunk id (the
old id names the whole chunk, which another download may still hold), same entity, same columns.
"""

from __future__ import annotations

import os
import struct
import time

import lz4.block
import pyarrow as pa
import pyarrow.compute as pc

from services.rrd.chunk import ChunkMeta, chunk_meta, read_chunk
from services.rrd.messages import ArrowMessage, Compression, chunk_id_str, tuid_proto
from services.rrd.pb import log_msg_pb2

_CHUNK_ID_KEY = b"rerun:id"


def new_chunk_id() -> bytes:
    """A fresh TUID: nanoseconds now, then a random increment (as Rerun makes them)."""
    return struct.pack(">QQ", time.time_ns(), int.from_bytes(os.urandom(8), "big"))


def trim(msg: ArrowMessage, meta: ChunkMeta, timeline: str, lo: int, hi: int) -> tuple[ArrowMessage, ChunkMeta] | None:
    """`msg` cut to the rows whose `timeline` value lies in [lo, hi]: the same message when all do,
    None when none do, else a new chunk."""
    batch = read_chunk(msg)
    index = next((i for i, f in enumerate(batch.schema)
                  if (f.metadata or {}).get(b"rerun:index_name", f.name.encode()).decode() == timeline
                  and (f.metadata or {}).get(b"rerun:kind") in (b"index", b"time")), None)
    if index is None:
        return None
    values = batch.column(index)
    values = values.view(pa.int64()) if values.type != pa.int64() else values
    mask = pc.and_(pc.greater_equal(values, lo), pc.less_equal(values, hi)).fill_null(False)
    kept = int(pc.sum(mask).as_py() or 0)
    if kept == batch.num_rows:
        return msg, meta
    if kept == 0:
        return None
    return reencode(msg, batch.filter(mask))


def reencode(msg: ArrowMessage, batch: pa.RecordBatch) -> tuple[ArrowMessage, ChunkMeta]:
    """A new chunk (new id) holding `batch`, in the store and with the compression of `msg`."""
    chunk_id = new_chunk_id()
    metadata = dict(batch.schema.metadata or {})
    metadata[_CHUNK_ID_KEY] = chunk_id_str(chunk_id).encode()
    batch = batch.replace_schema_metadata(metadata)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema) as writer:
        writer.write_batch(batch)
    ipc = sink.getvalue().to_pybytes()
    pb = log_msg_pb2.ArrowMsg.FromString(bytes(msg.raw))
    pb.payload = lz4.block.compress(ipc, store_size=False)
    pb.compression = int(Compression.LZ4)  # type: ignore[assignment]
    pb.uncompressed_size = len(ipc)
    pb.chunk_id.CopyFrom(tuid_proto(chunk_id))
    raw = pb.SerializeToString()
    trimmed = ArrowMessage(msg.offset, msg.stream_offset, msg.stream_index, raw, msg.store_id, chunk_id,
                           msg.is_static, Compression.LZ4, len(ipc), pb.payload)
    return trimmed, chunk_meta(trimmed)
