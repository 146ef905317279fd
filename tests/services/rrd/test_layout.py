"""The fast paths of chunk indexing agree with the plain ones on real recordings."""

from __future__ import annotations

import io

import pytest

from services.rrd import ArrowMessage, errors, iter_events
from services.rrd.chunk import _arrow_values, chunk_meta, decompress_payload, read_chunk
from services.rrd.decoder import LARGE_MESSAGE, RrdDecoder
from services.rrd.layout import read_batch_header, split_ipc
from services.rrd.pb import log_msg_pb2
from tests.services.rrd.recordings import Recording

sdk = pytest.mark.sdk


@sdk
def test_direct_batch_reading_equals_pyarrow(whole: Recording):
    """Row counts, timeline ranges and per-component ranges read from the IPC header directly are
    what pyarrow gives for the same chunk."""
    direct = 0
    for event in iter_events(whole.path):
        if not isinstance(event, ArrowMessage):
            continue
        meta = chunk_meta(event)
        rows, ranges, components = _arrow_values(read_chunk(event), meta.layout, event.offset)
        assert meta.num_rows == rows
        assert {t.name: t.range for t in meta.timelines} == ranges
        assert [(c.column, c.num_rows, c.ranges) for c in meta.components] == [
            (c.column, c.num_rows, c.ranges) for c in components
        ]
        # The cached layout describes this very schema (only the chunk id differs).
        assert meta.layout.schema.remove_metadata().equals(read_chunk(event).schema.remove_metadata())
        data = decompress_payload(event)
        split = split_ipc(data)
        assert split is not None
        direct += meta.layout.direct and read_batch_header(data, split[1], meta.layout) is not None
    assert direct > 0  # the fast path was taken (and checked above) for this recording


class _ReadOnly:
    """A stream with `read` but no `readinto`, like a socket wrapper or an HTTP body."""

    def __init__(self, data: bytes) -> None:
        self._data, self._pos = data, 0

    def read(self, size: int = -1) -> bytes:
        end = len(self._data) if size < 0 else self._pos + size
        piece, self._pos = self._data[self._pos : end], min(end, len(self._data))
        return piece


@sdk
def test_large_messages_keep_their_payload_in_place(recordings: dict[str, Recording]):
    rec = recordings["large"]
    events = [e for e in iter_events(rec.path) if isinstance(e, ArrowMessage)]
    large = [e for e in events if len(e.raw) >= LARGE_MESSAGE]
    assert len(large) >= 2  # the SDK batches the frames into a couple of large chunks
    for event in large:
        assert isinstance(event.payload, memoryview) and event.payload.obj is event.raw  # a view, not a copy
        assert bytes(event.payload) == log_msg_pb2.ArrowMsg.FromString(bytes(event.raw)).payload
    # The same events whether the source can `readinto` (files) or only `read`, and in odd pieces.
    without_readinto = [e for e in iter_events(_ReadOnly(rec.data)) if isinstance(e, ArrowMessage)]  # type: ignore[arg-type]
    decoder = RrdDecoder()
    pieces = [e for i in range(0, len(rec.data), 99_991) for e in decoder.feed(rec.data[i : i + 99_991])]
    decoder.finish()
    in_pieces = [e for e in pieces if isinstance(e, ArrowMessage)]
    for other in (without_readinto, in_pieces):
        assert [(e.offset, bytes(e.raw), bytes(e.payload)) for e in other] == [
            (e.offset, bytes(e.raw), bytes(e.payload)) for e in events
        ]


def test_large_message_cut_short_is_truncated_at_its_header():
    header = b"RRF2" + bytes([0, 41, 0, 0, 1, 2, 0, 0])
    body = bytes(LARGE_MESSAGE + 10)
    data = header + (2).to_bytes(8, "little") + len(body).to_bytes(8, "little") + body
    cut = data[:-5]
    for source in (io.BytesIO(cut), _ReadOnly(cut)):
        with pytest.raises(errors.TruncatedError) as info:
            list(iter_events(source))  # type: ignore[arg-type]
        assert info.value.offset == len(header)
