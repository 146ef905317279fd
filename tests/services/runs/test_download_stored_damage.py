"""A download never starts an answer it cannot finish: a chunk stored before ingest refused such
chunks (its values damaged) is sent as stored by an exact download instead of cutting the stream."""

from __future__ import annotations

import io
import struct

import lz4.block
import pyarrow as pa

from services.rrd import iter_events
from services.rrd.frames import MessageKind, StreamHeader
from services.rrd.messages import ArrowMessage, EndMessage
from services.runs.download import EntityFilter, TimeWindow, encode_run
from tests.services.rrd.synthetic import VERSION, _frame, arrow_body, chunk_id, chunk_ipc, store_info_body

RUN = "damaged-run"


def damaged_recording() -> bytes:
    """A header, SetStoreInfo, a chunk of 5 rows (frames 0-4) whose Scalars offsets decrease, and an
    intact chunk of 5 rows (frames 5-9)."""
    parts = [StreamHeader(VERSION).encode(), _frame(MessageKind.SET_STORE_INFO, store_info_body(RUN))]
    for i, frames in enumerate((range(0, 5), range(5, 10))):
        id_ = chunk_id(RUN, i)
        ipc = bytearray(chunk_ipc("/robot/speed", id_, list(frames), [[float(f)] for f in frames]))
        if i == 0:
            at = bytes(ipc).index(struct.pack("<6i", 0, 1, 2, 3, 4, 5))
            struct.pack_into("<i", ipc, at + 8, 4)  # offsets 0, 1, 4, 3, ...: not monotonic
        parts.append(_frame(MessageKind.ARROW_MSG, arrow_body(RUN, id_, bytes(ipc), static=False)))
    return b"".join(parts)


def test_an_exact_download_over_a_damaged_stored_chunk_finishes() -> None:
    events = list(iter_events(io.BytesIO(damaged_recording())))
    window = TimeWindow("frame", 2, 7, latest_at=False, exact=True)
    out = b"".join(
        bytes(p)
        for p in encode_run(events, EntityFilter([], []), blueprint=True, window=window, keep=None, picks={}, metas={})
    )
    decoded = list(iter_events(io.BytesIO(out)))  # the whole stream, with its End: nothing cut
    assert any(isinstance(e, EndMessage) for e in decoded)
    chunks = [e for e in decoded if isinstance(e, ArrowMessage)]
    assert len(chunks) == 2
    assert chunks[0].raw == next(e for e in events if isinstance(e, ArrowMessage)).raw  # sent as stored
    ipc = lz4.block.decompress(chunks[1].payload, uncompressed_size=chunks[1].uncompressed_size)
    rows = pa.ipc.open_stream(ipc).read_all()
    assert rows.column("frame").to_pylist() == [5, 6, 7]  # the intact chunk is trimmed to the window
