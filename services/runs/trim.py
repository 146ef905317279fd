"""`exact=true`: a chunk that straddles the time window is cut to the rows inside it.

The only case where a download re-encodes a payload: the kept rows become a new chunk with a new id (the
old id names the whole chunk, which another download may still hold), same entity, same columns.
"""

from __future__ import annotations

import os
import struct
import time
from collections.abc import Collection

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from services.rrd.chunk import ChunkMeta, chunk_meta, with_batch
from services.rrd.fieldmeta import rerun_key
from services.rrd.messages import ArrowMessage
from services.rrd.validate import validated_batch


def new_chunk_id() -> bytes:
    """A fresh TUID: nanoseconds now, then a random increment (as Rerun makes them)."""
    return struct.pack(">QQ", time.time_ns(), int.from_bytes(os.urandom(8), "big"))


def trim(
    msg: ArrowMessage, meta: ChunkMeta, timeline: str, lo: int, hi: int, also: Collection[int] = ()
) -> tuple[ArrowMessage, ChunkMeta] | None:
    """`msg` cut to the rows whose `timeline` value lies in [lo, hi], and the rows at positions `also`
    (latest-at rows before the window), in their order: the same message when all rows stay, None when
    none do, else a new chunk."""
    batch = validated_batch(msg, meta)  # its rows are filtered and re-encoded: every value is read
    index = next(
        (
            i
            for i, f in enumerate(batch.schema)
            if rerun_key(f, "index_name", f.name.encode()).decode() == timeline
            and rerun_key(f, "kind") in (b"index", b"time")
        ),
        None,
    )
    if index is None:
        return None
    values = batch.column(index)
    values = values.view(pa.int64()) if values.type != pa.int64() else values
    mask = pc.and_(pc.greater_equal(values, lo), pc.less_equal(values, hi)).fill_null(False)
    if also:
        picked = np.zeros(batch.num_rows, dtype=bool)
        picked[sorted(also)] = True
        mask = pc.or_(mask, pa.array(picked))
    kept = int(pc.sum(mask).as_py() or 0)
    if kept == batch.num_rows:
        return msg, meta
    if kept == 0:
        return None
    return reencode(msg, batch.filter(mask))


def reencode(msg: ArrowMessage, batch: pa.RecordBatch) -> tuple[ArrowMessage, ChunkMeta]:
    """A new chunk (new id) holding `batch`, in the store of `msg`."""
    trimmed = with_batch(msg, batch, chunk_id=new_chunk_id())
    return trimmed, chunk_meta(trimmed)
