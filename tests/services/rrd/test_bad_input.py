"""Hand-built bad inputs: every failure is a specific `RrdError` with the exact byte offset.

Everything here is built byte by byte with `struct`, protobuf and pyarrow (no recordings, no
SDK), so each test pins one problem to one offset:

  stream header  b"RRF2" + version[4] + [compression, serializer, 0, 0]      (12 bytes)
  message        u64 kind + u64 len + `len` bytes of protobuf                 (16 + len bytes)
  stream footer  u64 start + u64 len + u32 xxh32 + b"RRF2FOOT" + u32 count    (after End)
"""

from __future__ import annotations

import io
import struct
import subprocess
import sys
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lz4.block
import pyarrow as pa
import pytest
import xxhash

from services.rrd import errors
from services.rrd.chunk import chunk_meta, decompress_payload, read_chunk
from services.rrd.decoder import DEFAULT_MAX_MESSAGE_SIZE, RrdDecoder, decode_message, iter_events
from services.rrd.limits import DEFAULT_MAX_CHUNK_BYTES
from services.rrd.messages import (
    ArrowMessage,
    Compression,
    EndMessage,
    Event,
    StoreId,
    StoreInfoMessage,
    StoreKind,
    StreamFooter,
    StreamStart,
)
from services.rrd.pb import common_pb2, log_msg_pb2

# --- building blocks ------------------------------------------------------------------------

REPO_ROOT = Path(__file__).resolve().parents[3]
HEADER = b"RRF2" + bytes([0, 41, 0, 0]) + bytes([1, 2, 0, 0])
END, STORE_INFO, ARROW, BLUEPRINT = 0, 1, 2, 3
PB_NONE, PB_LZ4 = 1, 2  # the protobuf Compression enum (not the stream-header byte)
CRC_SEED = 7850921
CHUNK_ID_HEX = "18EA26BD96404E103c04e43dcbb199d4"
CHUNK_ID = bytes.fromhex(CHUNK_ID_HEX)


def header(
    version: bytes = bytes([0, 41, 0, 0]), options: bytes = bytes([1, 2, 0, 0]), magic: bytes = b"RRF2"
) -> bytes:
    return magic + version + options


def frame(kind: int, body: bytes) -> bytes:
    return struct.pack("<QQ", kind, len(body)) + body


def store_id_pb(recording_id: str = "rec-1", app: str = "app", kind: int = 1) -> common_pb2.StoreId:
    return common_pb2.StoreId(
        kind=kind,  # type: ignore[arg-type]
        recording_id=recording_id,
        application_id=common_pb2.ApplicationId(id=app),
    )


def store_info_body() -> bytes:
    info = log_msg_pb2.StoreInfo(
        store_id=store_id_pb(), store_version=log_msg_pb2.StoreVersion(crate_version_bits=0x2900)
    )
    return log_msg_pb2.SetStoreInfo(row_id=common_pb2.Tuid(time_ns=1, inc=2), info=info).SerializeToString()


def chunk_ipc(
    *,
    entity_path: bytes | None = b"/robot/speed",
    chunk_id: bytes | None = ("chunk_" + CHUNK_ID_HEX).encode(),
    frames: tuple[int, ...] = (5, 1, 3),
    scalars: tuple[list[float] | None, ...] = (None, [1.0], [2.0, 3.0]),
    with_index: bool = True,
) -> bytes:
    """A minimal Rerun chunk as an Arrow IPC stream: RowId, a `frame` sequence index, Scalars."""
    n = len(scalars)
    fields = [pa.field("rerun.controls.RowId", pa.binary(16), metadata={b"rerun:kind": b"control"})]
    columns: list[pa.Array] = [pa.array([i.to_bytes(16, "big") for i in range(n)], pa.binary(16))]
    if with_index:
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
    columns.append(pa.array(list(scalars), pa.list_(pa.float64())))
    metadata: dict[bytes, bytes] = {b"sorbet:version": b"0.1.3"}
    if entity_path is not None:
        metadata[b"rerun:entity_path"] = entity_path
    if chunk_id is not None:
        metadata[b"rerun:id"] = chunk_id
    schema = pa.schema(fields, metadata=metadata)
    sink = io.BytesIO()
    with pa.ipc.new_stream(sink, schema) as writer:
        writer.write_batch(pa.record_batch(columns, schema=schema))
    return sink.getvalue()


def arrow_body(
    ipc: bytes,
    *,
    compression: int = PB_LZ4,
    uncompressed_size: int | None = None,
    payload: bytes | None = None,
    chunk_id: bytes | None = None,
) -> bytes:
    """An ArrowMsg protobuf; the payload is LZ4-block compressed (no size prefix) by default."""
    if payload is None:
        payload = lz4.block.compress(ipc, store_size=False) if compression == PB_LZ4 else ipc
    pb = log_msg_pb2.ArrowMsg(
        store_id=store_id_pb(),
        compression=compression,  # type: ignore[arg-type]
        uncompressed_size=len(ipc) if uncompressed_size is None else uncompressed_size,
        encoding=log_msg_pb2.ENCODING_ARROW_IPC,
        payload=payload,
    )
    if chunk_id is not None:
        pb.chunk_id.CopyFrom(
            common_pb2.Tuid(time_ns=int.from_bytes(chunk_id[:8], "big"), inc=int.from_bytes(chunk_id[8:], "big"))
        )
    return pb.SerializeToString()


def stream_footer(footer_start: int, payload: bytes, *, crc: int | None = None, count: int = 1) -> bytes:
    crc = xxhash.xxh32_intdigest(payload, seed=CRC_SEED) if crc is None else crc
    return struct.pack("<QQI", footer_start, len(payload), crc) + b"RRF2FOOT" + struct.pack("<I", count)


# A valid prefix: header, SetStoreInfo, one Arrow chunk. Offsets 0, 12, 12 + 16 + len(info).
STORE_INFO_FRAME = frame(STORE_INFO, store_info_body())
GOOD_ARROW_FRAME = frame(ARROW, arrow_body(chunk_ipc()))
PREFIX = HEADER + STORE_INFO_FRAME + GOOD_ARROW_FRAME
PREFIX_EVENTS = [(0, StreamStart), (12, StoreInfoMessage), (12 + len(STORE_INFO_FRAME), ArrowMessage)]


def summary(events: list[Event]) -> list[tuple[int, type]]:
    return [(e.offset, type(e)) for e in events]


def check_error(exc: errors.RrdError, cls: type[errors.RrdError], offset: int) -> None:
    assert type(exc) is cls, f"expected {cls.__name__}, got {type(exc).__name__}: {exc}"
    assert isinstance(exc, errors.RrdError)
    assert exc.offset == offset, f"offset {exc.offset} != {offset}: {exc}"
    assert f"at byte {offset}" in str(exc), str(exc)
    assert exc.problem in str(exc)
    expected_status = 413 if cls is errors.MessageTooLargeError else 400
    assert exc.http_status() == expected_status


@dataclass
class Outcome:
    before: list[Event]  # events returned by feed() before the bad bytes were fed
    exc: errors.RrdError


def decode_expect(
    good: bytes, bad: bytes, cls: type[errors.RrdError], offset: int | tuple[int, ...], **decoder_args: int
) -> Outcome:
    """Feed `good` (must succeed), then `bad`, then finish(): the error must be `cls` at `offset`
    (or at one of `offset` if a tuple).

    The same input fed in one piece, and one byte at a time, must fail identically, after
    returning (at least) the events of `good`.
    """
    decoder = RrdDecoder(**decoder_args)
    before = decoder.feed(good)
    with pytest.raises(errors.RrdError) as info:
        decoder.feed(bad)
        decoder.finish()
    if isinstance(offset, tuple):
        assert info.value.offset in offset, f"offset {info.value.offset} not in {offset}: {info.value}"
        offset = info.value.offset
    check_error(info.value, cls, offset)

    whole_decoder = RrdDecoder(**decoder_args)
    whole_events: list[Event] = []
    with pytest.raises(errors.RrdError) as whole_info:
        whole_events += whole_decoder.feed(good + bad)
        whole_events += whole_decoder.finish()
    check_error(whole_info.value, cls, offset)
    assert summary(whole_events[: len(before)]) == summary(before)

    byte_decoder = RrdDecoder(**decoder_args)
    byte_events: list[Event] = []
    data = good + bad
    with pytest.raises(errors.RrdError) as byte_info:
        for i in range(len(data)):
            byte_events += byte_decoder.feed(data[i : i + 1])
        byte_events += byte_decoder.finish()
    check_error(byte_info.value, cls, offset)
    assert summary(byte_events[: len(before)]) == summary(before)
    assert all(e.offset < offset or isinstance(e, StreamFooter) for e in byte_events)
    return Outcome(before, info.value)


def decode_ok(data: bytes, **decoder_args: int) -> list[Any]:
    decoder = RrdDecoder(**decoder_args)
    return decoder.feed(data) + decoder.finish()


def one_arrow(body: bytes) -> ArrowMessage:
    events = decode_ok(PREFIX + frame(ARROW, body))
    msg = events[-1]
    assert isinstance(msg, ArrowMessage)
    return msg


LAST_OFFSET = len(PREFIX)  # where the message after the valid prefix starts


# --- the valid baseline ---------------------------------------------------------------------


def test_valid_prefix_decodes() -> None:
    events = decode_ok(PREFIX)
    assert summary(events) == PREFIX_EVENTS
    start, info, arrow = events
    assert start.version.to_bytes() == bytes([0, 41, 0, 0])
    assert info.store_id == StoreId(StoreKind.RECORDING, "app", "rec-1")
    assert str(info.sdk_version) == "0.41.0"
    assert arrow.store_id == info.store_id
    assert arrow.compression == Compression.LZ4
    assert arrow.chunk_id is None and arrow.is_static is None


def test_valid_minimal_chunk_meta() -> None:
    ipc = chunk_ipc()
    body = arrow_body(ipc)
    msg = one_arrow(body)
    assert decompress_payload(msg) == ipc
    assert read_chunk(msg).num_rows == 3
    meta = chunk_meta(msg)
    assert meta.chunk_id == CHUNK_ID  # from rerun:id, as the ArrowMsg carries no chunk_id
    assert meta.entity_path == "/robot/speed"
    assert meta.is_static is False
    assert meta.num_rows == 3
    assert meta.byte_size == len(body) == msg.size
    assert meta.uncompressed_size == len(ipc)
    assert meta.row_id_field is not None and meta.row_id_field.name == "rerun.controls.RowId"
    (timeline,) = meta.timelines
    assert (timeline.name, timeline.type, timeline.is_sorted) == ("frame", "sequence", False)
    assert (timeline.range.min, timeline.range.max) == (1, 5)
    (component,) = meta.components
    assert component.column == "Scalars:scalars"
    assert component.component == "Scalars:scalars"
    assert component.archetype == "rerun.archetypes.Scalars"
    assert component.component_type is None
    assert component.descriptor == ("rerun.archetypes.Scalars", "Scalars:scalars", "")
    assert component.num_rows == 2  # the first row is null
    assert {name: (r.min, r.max) for name, r in component.ranges.items()} == {"frame": (1, 3)}
    assert meta.archetypes == {"rerun.archetypes.Scalars"}


def test_valid_chunk_uncompressed_static_with_protobuf_chunk_id() -> None:
    ipc = chunk_ipc(with_index=False, chunk_id=None, scalars=([1.0],))
    other_id = bytes(range(16))
    msg = one_arrow(arrow_body(ipc, compression=PB_NONE, chunk_id=other_id))
    assert msg.chunk_id == other_id and msg.compression == Compression.NONE
    meta = chunk_meta(msg)
    assert meta.chunk_id == other_id
    assert meta.is_static is True and meta.timelines == ()
    assert meta.num_rows == 1 and meta.components[0].num_rows == 1
    assert meta.components[0].ranges == {}


def test_offsets_count_from_start_offset() -> None:
    """`.offset` is absolute: a decoder started at byte 1000 of a larger input reports 1000 + n."""
    bad = header(options=bytes([1, 2, 0, 7]))
    decoder = RrdDecoder(start_offset=1000)
    with pytest.raises(errors.ReservedBytesError) as info:
        decoder.feed(bad)
        decoder.finish()
    check_error(info.value, errors.ReservedBytesError, 1010)


# --- one test per error ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "data",
    [
        b"PK\x03\x04" + bytes(40),  # a zip file
        b"\x89PNG\r\n\x1a\n" + bytes(8),
        b"RRF3" + bytes([0, 41, 0, 0, 1, 2, 0, 0]),
        b"rrf2" + bytes([0, 41, 0, 0, 1, 2, 0, 0]),
        b"NOPE",  # exactly 4 bytes
    ],
    ids=["zip", "png", "RRF3", "lowercase", "four-bytes"],
)
def test_not_an_rrd(data: bytes) -> None:
    decode_expect(b"", data, errors.NotAnRrdError, 0)


def test_empty_input_is_not_an_rrd() -> None:
    with pytest.raises(errors.NotAnRrdError) as info:
        RrdDecoder().finish()
    check_error(info.value, errors.NotAnRrdError, 0)


@pytest.mark.parametrize("data", [b"{}\n", b"GI", b"\x00"], ids=["json", "two-bytes", "nul"])
def test_tiny_non_rrd_input_is_not_an_rrd(data: bytes) -> None:
    """A 1-3 byte input that cannot start b"RRF2" is not an RRD, not a truncated one."""
    decode_expect(b"", data, errors.NotAnRrdError, 0)


def test_garbage_after_end_is_a_footer_error() -> None:
    """After End comes a stream footer or a new stream; anything else is a malformed footer."""
    good = HEADER + STORE_INFO_FRAME + frame(END, b"\x12\x00")
    outcome = decode_expect(good, b"garbage!" * 3, errors.FooterError, len(good))
    assert summary(outcome.before) == [
        (0, StreamStart),
        (12, StoreInfoMessage),
        (12 + len(STORE_INFO_FRAME), EndMessage),
    ]


def test_garbage_after_a_complete_stream_is_not_an_rrd() -> None:
    """After End + stream footer a new stream may start; 8+ bytes of anything else are not RRD."""
    end_body = b"\x12\x00"  # a non-empty RrdFooter (one unknown empty field)
    good = HEADER + STORE_INFO_FRAME + frame(END, end_body)
    good += stream_footer(12 + len(STORE_INFO_FRAME) + 16, end_body)
    outcome = decode_expect(good, b"garbage!" * 3, errors.NotAnRrdError, len(good))
    assert [type(e) for e in outcome.before] == [StreamStart, StoreInfoMessage, EndMessage, StreamFooter]


@pytest.mark.parametrize("magic", [b"RRF0", b"RRF1"])
def test_old_rrf_generations_are_unsupported(magic: bytes) -> None:
    outcome = decode_expect(b"", header(magic=magic) + STORE_INFO_FRAME, errors.UnsupportedVersionError, 0)
    assert magic.decode() in str(outcome.exc)
    assert outcome.exc.code.value == "UNSUPPORTED_RRD_VERSION"


@pytest.mark.parametrize("version", [bytes([0, 22, 9, 0]), bytes([0, 9, 0, 0]), bytes([0, 22, 0, 0x81])])
def test_versions_before_0_23_are_unsupported(version: bytes) -> None:
    outcome = decode_expect(b"", header(version=version), errors.UnsupportedVersionError, 4)
    assert "0.23" in str(outcome.exc)


@pytest.mark.parametrize("version", [bytes([0, 23, 0, 0]), bytes([0, 0, 0, 0]), bytes([1, 2, 3, 0x41])])
def test_supported_versions_decode(version: bytes) -> None:
    events = decode_ok(header(version=version) + STORE_INFO_FRAME)
    assert summary(events) == [(0, StreamStart), (12, StoreInfoMessage)]
    assert events[0].version.to_bytes() == version


def test_stream_header_compression_off_is_accepted() -> None:
    events = decode_ok(header(options=bytes([0, 2, 0, 0])) + STORE_INFO_FRAME)
    assert events[0].header.compression == 0


@pytest.mark.parametrize("byte", [2, 3, 0xFF])
def test_unknown_stream_compression(byte: int) -> None:
    decode_expect(b"", header(options=bytes([byte, 2, 0, 0])), errors.UnknownCompressionError, 8)


def test_unknown_arrow_message_compression() -> None:
    bad = frame(ARROW, arrow_body(chunk_ipc(), compression=7, payload=b"xx"))
    outcome = decode_expect(PREFIX, bad, errors.UnknownCompressionError, LAST_OFFSET)
    assert summary(outcome.before) == PREFIX_EVENTS


@pytest.mark.parametrize("byte", [0, 1, 3, 0xFF])
def test_unknown_serializer(byte: int) -> None:
    outcome = decode_expect(b"", header(options=bytes([1, byte, 0, 0])), errors.UnknownSerializerError, 9)
    if byte == 1:
        assert "MsgPack" in str(outcome.exc)


@pytest.mark.parametrize("reserved", [bytes([1, 0]), bytes([0, 1]), bytes([0xFF, 0xFF])])
def test_non_zero_reserved_bytes(reserved: bytes) -> None:
    decode_expect(b"", header(options=bytes([1, 2]) + reserved), errors.ReservedBytesError, 10)


def test_bad_header_of_second_concatenated_stream() -> None:
    """A concatenated stream's header is checked too, at its own absolute offset."""
    first = HEADER + STORE_INFO_FRAME
    outcome = decode_expect(
        first, header(options=bytes([1, 2, 0, 9])) + STORE_INFO_FRAME, errors.ReservedBytesError, len(first) + 10
    )
    assert summary(outcome.before) == [(0, StreamStart), (12, StoreInfoMessage)]


def test_message_over_configured_limit() -> None:
    body = store_info_body()
    limit = len(body) - 1
    outcome = decode_expect(HEADER, frame(STORE_INFO, body), errors.MessageTooLargeError, 12, max_message_size=limit)
    assert str(limit) in str(outcome.exc)
    assert outcome.exc.http_status() == 413
    assert outcome.exc.code.value == "MESSAGE_TOO_LARGE"
    # Exactly at the limit is fine.
    events = decode_ok(HEADER + frame(STORE_INFO, body), max_message_size=len(body))
    assert summary(events) == [(0, StreamStart), (12, StoreInfoMessage)]


def test_default_message_limit_is_256_mib() -> None:
    assert DEFAULT_MAX_MESSAGE_SIZE == 256 * 1024 * 1024
    over = struct.pack("<QQ", ARROW, DEFAULT_MAX_MESSAGE_SIZE + 1)
    decode_expect(PREFIX, over, errors.MessageTooLargeError, LAST_OFFSET)


@pytest.mark.parametrize("length", [2**62, 2**64 - 1])
def test_huge_declared_length_raises_at_once_without_allocating(length: int) -> None:
    """Refused from the header alone: no payload byte is needed (nor awaited) and nothing is
    reserved for it. The fault may surface from the feed() that carried the header or from the
    next call, here an empty feed()."""
    decoder = RrdDecoder()
    before = decoder.feed(PREFIX)
    tracemalloc.start()
    started = time.monotonic()
    try:
        with pytest.raises(errors.MessageTooLargeError) as info:
            assert decoder.feed(struct.pack("<QQ", ARROW, length)) == []  # only the header
            decoder.feed(b"")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert time.monotonic() - started < 1.0
    assert peak < 1 << 20, f"{peak} bytes allocated while refusing a {length}-byte message"
    check_error(info.value, errors.MessageTooLargeError, LAST_OFFSET)
    assert summary(before) == PREFIX_EVENTS


def test_large_message_under_the_limit_is_not_allocated_up_front() -> None:
    """A 200 MiB message announced but never sent: nothing is reserved for it, finish() says truncated."""
    decoder = RrdDecoder()
    decoder.feed(PREFIX)
    tracemalloc.start()
    try:
        assert decoder.feed(struct.pack("<QQ", ARROW, 200 << 20) + b"abc") == []
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20
    with pytest.raises(errors.TruncatedError) as info:
        decoder.finish()
    check_error(info.value, errors.TruncatedError, LAST_OFFSET)


@pytest.mark.parametrize("kind", [4, 5, 255, 2**32, 2**64 - 1])
def test_unknown_message_kind(kind: int) -> None:
    bad = struct.pack("<QQ", kind, 3) + b"abc"
    outcome = decode_expect(PREFIX, bad, errors.UnknownMessageKindError, LAST_OFFSET)
    assert summary(outcome.before) == PREFIX_EVENTS
    assert str(kind) in str(outcome.exc)


def test_unknown_kind_is_reported_before_the_size_limit() -> None:
    decode_expect(PREFIX, struct.pack("<QQ", 9, 2**63), errors.UnknownMessageKindError, LAST_OFFSET)


def test_truncated_payload() -> None:
    whole = frame(ARROW, arrow_body(chunk_ipc()))
    outcome = decode_expect(PREFIX, whole[:-1], errors.TruncatedError, LAST_OFFSET)
    assert summary(outcome.before) == PREFIX_EVENTS
    assert "ARROW_MSG" in str(outcome.exc)


@pytest.mark.parametrize("cut", [1, 8, 15])
def test_truncated_message_header(cut: int) -> None:
    decode_expect(PREFIX, frame(STORE_INFO, store_info_body())[:cut], errors.TruncatedError, LAST_OFFSET)


@pytest.mark.parametrize("cut", [4, 11])
def test_truncated_stream_header(cut: int) -> None:
    decode_expect(b"", HEADER[:cut], errors.TruncatedError, 0)


def test_truncated_stream_footer() -> None:
    end_body = b"\x12\x00"  # a non-empty RrdFooter (one unknown empty field)
    good = PREFIX + frame(END, end_body)
    footer = stream_footer(len(PREFIX) + 16, end_body)
    for cut in (1, 8, 19):  # inside the 20-byte entry: reported at the trailer's start
        decode_expect(good, footer[:cut], errors.TruncatedError, len(good))
    for cut in (21, 28, 31):  # the entry is complete: where the trailer or its fixed part starts
        decode_expect(good, footer[:cut], errors.TruncatedError, (len(good), len(good) + 20))


def test_stream_footer_cut_after_its_entry_is_truncated() -> None:
    """The 32-byte trailer cut after the 20-byte entry (before b"RRF2FOOT") is a torn file."""
    good = PREFIX + frame(END, b"\x12\x00")
    footer = stream_footer(len(PREFIX) + 16, b"\x12\x00")
    decoder = RrdDecoder()
    decoder.feed(good)
    assert decoder.feed(footer[:20]) == []  # the trailer is reported only once whole
    with pytest.raises(errors.RrdError) as info:
        decoder.finish()
    check_error(info.value, errors.TruncatedError, len(good))  # where the trailer starts


@pytest.mark.parametrize(
    ("kind", "body"),
    [
        (STORE_INFO, b"\xff\xff\xff"),
        (ARROW, b"\x0a\xff\xff\xff\xff\x0f"),  # a length-delimited field longer than the message
        (BLUEPRINT, b"\x08"),  # a varint tag with no value
        (END, b"\x0a\x05ab"),
        (STORE_INFO, log_msg_pb2.SetStoreInfo().SerializeToString()),  # parses, but no store_id
    ],
    ids=["store-info", "arrow", "blueprint", "end", "no-store-id"],
)
def test_protobuf_does_not_parse(kind: int, body: bytes) -> None:
    outcome = decode_expect(PREFIX, frame(kind, body), errors.ProtobufError, LAST_OFFSET)
    assert summary(outcome.before) == PREFIX_EVENTS


def test_arrow_message_with_unknown_encoding() -> None:
    pb = log_msg_pb2.ArrowMsg.FromString(arrow_body(chunk_ipc()))
    pb.encoding = 5  # type: ignore[assignment]
    decode_expect(PREFIX, frame(ARROW, pb.SerializeToString()), errors.ProtobufError, LAST_OFFSET)


@pytest.mark.parametrize("delta", [-1, 1, 1000, 2**20])
def test_lz4_does_not_decompress_to_uncompressed_size(delta: int) -> None:
    ipc = chunk_ipc()
    msg = one_arrow(arrow_body(ipc, uncompressed_size=len(ipc) + delta))
    assert msg.offset == LAST_OFFSET
    for reader in (chunk_meta, read_chunk, decompress_payload):
        with pytest.raises(errors.RrdError) as info:
            reader(msg)
        check_error(info.value, errors.DecompressionError, LAST_OFFSET)


@pytest.mark.parametrize("declared", [DEFAULT_MAX_CHUNK_BYTES + 1, 2**31, 2**40, 2**64 - 1])
def test_declared_size_over_the_chunk_limit(declared: int) -> None:
    """A chunk declaring more than FLEET_MAX_CHUNK_BYTES uncompressed is refused as the message is
    decoded, before any decompression (an LZ4 bomb: 255x its size), naming the setting."""
    body = arrow_body(chunk_ipc(), uncompressed_size=declared)
    outcome = decode_expect(PREFIX, frame(ARROW, body), errors.MessageTooLargeError, LAST_OFFSET)
    assert "FLEET_MAX_CHUNK_BYTES" in str(outcome.exc)
    assert summary(outcome.before) == PREFIX_EVENTS
    # A reader given such a message some other way refuses it too, before allocating.
    msg = decode_ok(PREFIX + frame(ARROW, body), max_chunk_bytes=2**64)[-1]
    assert isinstance(msg, ArrowMessage)
    for reader in (chunk_meta, read_chunk, decompress_payload):
        with pytest.raises(errors.RrdError) as info:
            reader(msg)
        check_error(info.value, errors.MessageTooLargeError, LAST_OFFSET)


def test_chunk_limit_is_a_decoder_setting() -> None:
    ipc = chunk_ipc(frames=tuple(range(100)), scalars=tuple([1.0] for _ in range(100)))  # larger than PREFIX's
    body = arrow_body(ipc)
    decode_expect(PREFIX, frame(ARROW, body), errors.MessageTooLargeError, LAST_OFFSET, max_chunk_bytes=len(ipc) - 1)
    assert isinstance(decode_ok(PREFIX + frame(ARROW, body), max_chunk_bytes=len(ipc))[-1], ArrowMessage)
    raw = one_arrow(body).raw
    with pytest.raises(errors.MessageTooLargeError):
        decode_message(ARROW, raw, max_chunk_bytes=len(ipc) - 1)


@pytest.mark.parametrize("payload", [b"", b"\xff", b"\xf0" + bytes(20), b"not lz4 at all"])
def test_lz4_garbage(payload: bytes) -> None:
    msg = one_arrow(arrow_body(chunk_ipc(), payload=payload, uncompressed_size=100))
    with pytest.raises(errors.RrdError) as info:
        chunk_meta(msg)
    check_error(info.value, errors.DecompressionError, LAST_OFFSET)


def _schema_only_ipc() -> bytes:
    sink = io.BytesIO()
    schema = pa.schema([pa.field("x", pa.int64())], metadata={b"rerun:entity_path": b"/a"})
    with pa.ipc.new_stream(sink, schema):
        pass
    return sink.getvalue()


@pytest.mark.parametrize(
    "ipc",
    [
        chunk_ipc(entity_path=None),
        chunk_ipc(chunk_id=None),  # no rerun:id and no ArrowMsg.chunk_id
        chunk_ipc(chunk_id=b"chunk_not-hex"),
        b"this is not Arrow IPC at all, just text " * 3,
        _schema_only_ipc(),  # a schema, but no record batch
        chunk_ipc()[:-40],  # the record batch cut short
    ],
    ids=["no-entity-path", "no-chunk-id", "bad-chunk-id", "text", "schema-only", "cut-batch"],
)
@pytest.mark.parametrize("compression", [PB_LZ4, PB_NONE], ids=["lz4", "none"])
def test_arrow_payload_that_is_not_a_chunk(ipc: bytes, compression: int) -> None:
    msg = one_arrow(arrow_body(ipc, compression=compression))
    assert msg.offset == LAST_OFFSET
    with pytest.raises(errors.RrdError) as info:
        chunk_meta(msg)
    check_error(info.value, errors.NotAChunkError, LAST_OFFSET)


def test_index_column_of_unsupported_type_is_not_a_chunk() -> None:
    schema = pa.schema(
        [pa.field("frame", pa.string(), metadata={b"rerun:kind": b"index"})],
        metadata={b"rerun:entity_path": b"/a", b"rerun:id": ("chunk_" + CHUNK_ID_HEX).encode()},
    )
    sink = io.BytesIO()
    with pa.ipc.new_stream(sink, schema) as writer:
        writer.write_batch(pa.record_batch([pa.array(["x"])], schema=schema))
    msg = one_arrow(arrow_body(sink.getvalue()))
    with pytest.raises(errors.RrdError) as info:
        chunk_meta(msg)
    check_error(info.value, errors.NotAChunkError, LAST_OFFSET)


@pytest.mark.parametrize("where", [b"rerun:component", b"rerun:archetype", b"rerun:index_name", b"rerun:entity_path"])
def test_non_utf8_metadata_is_not_a_chunk(where: bytes) -> None:
    """Damaged (non-UTF-8) Rerun metadata must be reported as NotAChunkError, not UnicodeDecodeError."""
    ipc = chunk_ipc()
    sink = io.BytesIO()
    batch = pa.ipc.open_stream(ipc).read_next_batch()
    schema = batch.schema
    if where == b"rerun:entity_path":
        schema = schema.with_metadata({**schema.metadata, where: b"/\xff\xfe"})
    else:
        fields = []
        for fld in schema:
            meta = dict(fld.metadata or {})
            if where in meta:
                meta[where] = b"\xc3\x28"
            fields.append(fld.with_metadata(meta))
        schema = pa.schema(fields, metadata=schema.metadata)
    with pa.ipc.new_stream(sink, schema) as writer:
        writer.write_batch(pa.record_batch(batch.columns, schema=schema))
    msg = one_arrow(arrow_body(sink.getvalue()))
    with pytest.raises(errors.RrdError) as info:
        chunk_meta(msg)
    check_error(info.value, errors.NotAChunkError, LAST_OFFSET)


def _chunk_with_lengths(n: int) -> bytes:
    """The minimal chunk (3 rows) with the record batch and field-node lengths in its IPC metadata
    set to `n`, buffers left at 3 rows: lengths are consistent, buffers far too small."""
    ipc = bytearray(chunk_ipc(scalars=([1.0], [2.0], [3.0])))
    (schema_len,) = struct.unpack_from("<i", ipc, 4)
    batch = 8 + schema_len
    assert ipc[batch : batch + 4] == b"\xff\xff\xff\xff"
    (meta_len,) = struct.unpack_from("<i", ipc, batch + 4)
    three = struct.pack("<q", 3)
    spots = [i for i in range(batch + 8, batch + 8 + meta_len) if ipc[i : i + 8] == three]
    assert len(spots) == 5  # batch length, RowId, frame, Scalars and its child values
    for i in spots:
        ipc[i : i + 8] = struct.pack("<q", n)
    return bytes(ipc)


_ISOLATED_CHUNK_META = """
import sys
from services.rrd.chunk import chunk_meta
from services.rrd.decoder import RrdDecoder
from services.rrd.errors import RrdError
decoder = RrdDecoder()
events = decoder.feed(sys.stdin.buffer.read()) + decoder.finish()
try:
    chunk_meta(events[-1])
    print("ok")
except RrdError as exc:
    print(type(exc).__name__, exc.offset)
"""


@pytest.mark.parametrize("compression", [PB_LZ4, PB_NONE], ids=["lz4", "none"])
def test_buffers_smaller_than_declared_lengths_do_not_crash(compression: int) -> None:
    """Arrow metadata claiming 2**40 rows over 3 rows of buffers: NotAChunkError, not a segfault
    (run in a subprocess so that a crash fails this test only)."""
    data = PREFIX + frame(ARROW, arrow_body(_chunk_with_lengths(1 << 40), compression=compression))
    done = subprocess.run(
        [sys.executable, "-X", "faulthandler", "-c", _ISOLATED_CHUNK_META],
        input=data,
        capture_output=True,
        timeout=60,
        check=False,
        cwd=REPO_ROOT,
    )
    assert done.returncode == 0, f"exit status {done.returncode}\n{done.stderr.decode(errors='replace')}"
    assert done.stdout.decode().split() == ["NotAChunkError", str(LAST_OFFSET)]


def _footer_case(
    *, crc_delta: int = 0, length_delta: int = 0, count: int = 1, start_delta: int = 0
) -> tuple[bytes, bytes, int]:
    end_body = log_msg_pb2.RrdFooter().SerializeToString() + b"\x12\x00"  # an unknown field: 2 bytes
    assert len(end_body) == 2
    good = PREFIX + frame(END, end_body)
    crc = xxhash.xxh32_intdigest(end_body, seed=CRC_SEED) ^ crc_delta
    footer_start = len(PREFIX) + 16 + start_delta
    trailer = struct.pack("<QQI", footer_start, len(end_body) + length_delta, crc)
    trailer += b"RRF2FOOT" + struct.pack("<I", count)
    return good, trailer, len(good)


def test_valid_footer_decodes() -> None:
    good, trailer, at = _footer_case()
    events = decode_ok(good + trailer)
    assert summary(events) == [*PREFIX_EVENTS, (LAST_OFFSET, EndMessage), (at, StreamFooter)]
    footer = events[-1]
    assert (footer.footer_start, footer.footer_length) == (LAST_OFFSET + 16, 2)


@pytest.mark.parametrize("crc_delta", [1, 0x80000000, 0xFFFFFFFF])
def test_bad_footer_crc(crc_delta: int) -> None:
    good, trailer, at = _footer_case(crc_delta=crc_delta)
    outcome = decode_expect(good, trailer, errors.FooterError, at)
    assert summary(outcome.before) == [*PREFIX_EVENTS, (LAST_OFFSET, EndMessage)]
    assert "CRC" in str(outcome.exc)


@pytest.mark.parametrize(
    ("case", "offset_delta"),
    [
        ({"length_delta": 1}, 0),
        ({"count": 2}, 20),  # the fixed part after the one entry
        ({"count": 0}, 20),
        ({"start_delta": 1}, 0),  # points elsewhere: neither a footer nor a new stream
    ],
)
def test_malformed_footer(case: dict[str, int], offset_delta: int) -> None:
    good, trailer, at = _footer_case(**case)
    decode_expect(good, trailer, errors.FooterError, at + offset_delta)


@pytest.mark.parametrize(
    "bad",
    [
        struct.pack("<QQ", 9, 0),  # unknown kind
        frame(STORE_INFO, b"\xff\xff"),  # protobuf
        header(options=bytes([1, 2, 0, 1])),  # a second stream with a bad header
    ],
    ids=["kind", "protobuf", "header"],
)
def test_error_is_sticky(bad: bytes) -> None:
    """After a fault nothing more is decoded: every later feed() and finish() raises it again."""
    decoder = RrdDecoder()
    assert summary(decoder.feed(PREFIX)) == PREFIX_EVENTS
    more = [bad, STORE_INFO_FRAME, GOOD_ARROW_FRAME, HEADER + STORE_INFO_FRAME, STORE_INFO_FRAME]
    first: errors.RrdError | None = None
    for piece in more:
        try:
            events = decoder.feed(piece)
        except errors.RrdError as exc:
            if first is None:
                first = exc
            assert (type(exc), exc.offset) == (type(first), first.offset)
        else:
            assert first is None, "feed() returned after a fault"
            assert events == []  # nothing after the bad bytes decodes
    assert first is not None and first.offset >= LAST_OFFSET
    with pytest.raises(errors.RrdError) as last:
        decoder.finish()
    assert (type(last.value), last.value.offset) == (type(first), first.offset)


@pytest.mark.parametrize(
    "before", [b"", PREFIX, PREFIX + frame(END, b"\x12\x00")], ids=["alone", "after-messages", "after-end"]
)
def test_stream_header_alone_at_end_of_input(before: bytes) -> None:
    """A (next) stream that has only its 12-byte header so far: a StreamStart, not a truncation."""
    decoder = RrdDecoder()
    events = decoder.feed(before + HEADER)
    events += decoder.finish()
    assert summary(events)[-1] == (len(before), StreamStart)


# --- zero-length messages ------------------------------------------------------------------

_EMPTY_END_FOOTER = stream_footer(len(HEADER) + 16, b"")


@pytest.mark.parametrize(
    ("data", "kinds"),
    [
        (HEADER + frame(END, b"") + _EMPTY_END_FOOTER, [StreamStart, EndMessage, StreamFooter]),
        (HEADER + frame(END, b"") + HEADER, [StreamStart, EndMessage, StreamStart]),  # RrdEncoder(write_footer=False)
        (HEADER + frame(BLUEPRINT, b"") + frame(END, b""), [StreamStart, "BlueprintActivationMessage", EndMessage]),
        (HEADER + frame(ARROW, b"") + STORE_INFO_FRAME, [StreamStart, ArrowMessage, StoreInfoMessage]),
    ],
    ids=["end-then-footer", "end-then-stream", "blueprint-then-end", "arrow-then-store-info"],
)
def test_zero_length_message_followed_by_more_input(data: bytes, kinds: list[type | str]) -> None:
    """A message with an empty protobuf payload (valid protobuf: all fields default) must not stall
    the decoder: what follows it in the same feed() is decoded, and finish() succeeds."""
    decoder = RrdDecoder()
    events = decoder.feed(data)
    events += decoder.finish()
    names = [k if isinstance(k, str) else k.__name__ for k in kinds]
    assert [type(e).__name__ for e in events] == names


# --- the error classes ----------------------------------------------------------------------

ALL_ERRORS = [
    errors.NotAnRrdError,
    errors.UnsupportedVersionError,
    errors.UnknownCompressionError,
    errors.UnknownSerializerError,
    errors.ReservedBytesError,
    errors.UnknownMessageKindError,
    errors.MessageTooLargeError,
    errors.TruncatedError,
    errors.ProtobufError,
    errors.DecompressionError,
    errors.NotAChunkError,
    errors.NotArrowError,
    errors.InvalidChunkError,
    errors.FooterError,
]


@pytest.mark.parametrize("cls", ALL_ERRORS, ids=lambda cls: cls.__name__)
def test_error_classes_carry_offset_and_status(cls: type[errors.RrdError]) -> None:
    exc = cls("some detail", 1234)
    assert isinstance(exc, errors.RrdError)
    assert exc.offset == 1234 and exc.detail == "some detail"
    assert str(exc) == f"{cls.problem} at byte 1234: some detail"
    assert cls.problem != errors.RrdError.problem  # each names its own problem
    if cls is errors.MessageTooLargeError:
        assert (exc.http_status(), exc.grpc_status()) == (413, "RESOURCE_EXHAUSTED")
    else:
        assert (exc.http_status(), exc.grpc_status()) == (400, "INVALID_ARGUMENT")
    assert exc.to_dict() == {"code": cls.code.value, "message": str(exc)}


def test_every_error_class_is_listed() -> None:
    defined = {
        obj
        for obj in vars(errors).values()
        if isinstance(obj, type) and issubclass(obj, errors.RrdError) and obj is not errors.RrdError
    }
    assert defined == set(ALL_ERRORS)
    assert len({cls.problem for cls in ALL_ERRORS}) == len(ALL_ERRORS)


# --- iter_events keeps what came before the fault -------------------------------------------


@pytest.mark.parametrize(
    ("bad", "cls"),
    [
        (struct.pack("<QQ", 9, 0), errors.UnknownMessageKindError),
        (frame(STORE_INFO, b"\xff\xff"), errors.ProtobufError),
        (frame(ARROW, arrow_body(chunk_ipc()))[:-1], errors.TruncatedError),
    ],
    ids=["kind", "protobuf", "truncated"],
)
def test_iter_events_yields_everything_before_the_fault(bad: bytes, cls: type[errors.RrdError]) -> None:
    """docs/rrd-codec.md: "Messages returned before the fault stay valid"; iter_events: "Raises the
    codec error at the end (after yielding everything before it)" -- also when the whole input
    arrives in one read."""
    got: list[Event] = []
    with pytest.raises(errors.RrdError) as info:
        got.extend(iter_events(io.BytesIO(PREFIX + bad)))
    check_error(info.value, cls, LAST_OFFSET)
    assert summary(got) == PREFIX_EVENTS
