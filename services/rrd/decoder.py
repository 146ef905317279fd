"""Incremental RRD stream reader.

Feed it bytes as they arrive (an HTTP body, a socket, a file read in pieces): it keeps only the
bytes of the message in progress and returns the typed messages completed so far, with their
byte offsets. It handles several stores in one stream, repeated SetStoreInfo, files with or
without footer, concatenated streams (with or without End between them), and reports a torn
last message from `finish()` after everything before it was returned. Store ids written before
Rerun 0.25 (no application id) are completed from the stream's SetStoreInfo (see store_ids.py).
"""

from __future__ import annotations

import enum
import os
import struct
from collections.abc import Iterator
from typing import BinaryIO

from google.protobuf.message import DecodeError

from services.rrd import errors, limits, protowire
from services.rrd.frames import (
    FOOTER_ENTRY_SIZE,
    FOOTER_FIXED_SIZE,
    FOOTER_MAGIC,
    FOURCC,
    MESSAGE_HEADER_SIZE,
    STREAM_HEADER_SIZE,
    MessageKind,
    RerunVersion,
    decode_footer_entry,
    decode_message_header,
    decode_stream_header,
    footer_crc,
    looks_like_stream_header,
)
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    Buffer,
    Compression,
    EndMessage,
    Event,
    Message,
    StoreId,
    StoreInfoMessage,
    StreamFooter,
    StreamStart,
    tuid_bytes,
)
from services.rrd.pb import common_pb2, log_msg_pb2
from services.rrd.store_ids import StoreIdResolver

DEFAULT_MAX_MESSAGE_SIZE = 256 * 1024 * 1024
READ_SIZE = 1024 * 1024
LARGE_MESSAGE = 256 * 1024
LARGE_STEP = 8 * 1024 * 1024
_R = ord("R")
_MESSAGE_HEADER = struct.Struct("<QQ")


class _State(enum.Enum):
    STREAM_HEADER = 0
    MESSAGE_HEADER = 1
    PAYLOAD = 2
    AFTER_END = 3


class RrdDecoder:
    """Push decoder: `feed(data)` returns the events completed by `data`; `finish()` at EOF."""

    def __init__(
        self,
        *,
        max_message_size: int = DEFAULT_MAX_MESSAGE_SIZE,
        max_chunk_bytes: int | None = None,
        start_offset: int = 0,
    ) -> None:
        self.max_message_size = max_message_size
        # Largest chunk an Arrow message may declare (default: the process's FLEET_MAX_CHUNK_BYTES).
        self.max_chunk_bytes = max_chunk_bytes if max_chunk_bytes is not None else limits.max_chunk_bytes()
        self._buf = bytearray()
        self._buf_offset = start_offset  # absolute offset of _buf[0]
        self._state = _State.STREAM_HEADER
        self._streams = 0
        self._stream_offset = start_offset
        self._msg_offset = 0
        self._kind = 0
        self._length = 0
        self._end: tuple[int, int, bytes] | None = None  # (stream-relative start, len, payload)
        self._footer_entries: list[tuple[int, int, int, int, int]] = []  # StreamFooter fields
        self._error: errors.RrdError | None = None
        self._large: bytearray | None = None  # the message being read when it is large
        self._filled = 0
        self._store_ids = StoreIdResolver()  # pre-0.25 streams: application ids from SetStoreInfo

    @property
    def offset(self) -> int:
        """Absolute offset of the first byte not yet consumed."""
        return self._buf_offset

    @property
    def streams(self) -> int:
        return self._streams

    def feed(self, data: bytes | bytearray | memoryview) -> list[Event]:
        """Take the next bytes; return the events they complete.

        A fault found in `data` is raised by the *next* call (`feed` or `finish`), so the events
        completed before the fault are always returned first."""
        self._raise_pending()
        if not data:
            return []
        events: list[Event] = []
        if self._large is not None:
            taken = self._fill_large(data, events)
            if taken == len(data) or self._error is not None:
                return events
            data = memoryview(data)[taken:]
        self._buf += data
        pos = 0
        buf = self._buf
        try:
            while True:
                if self._state is _State.MESSAGE_HEADER:
                    pos = self._whole_messages(buf, pos, events)
                step = self._step(buf, pos, events)
                if step is None:
                    break
                pos += step
        except errors.RrdError as exc:
            self._error = exc
        finally:
            if pos:
                del buf[:pos]
                self._buf_offset += pos
        return events

    def _whole_messages(self, buf: bytearray, pos: int, events: list[Event]) -> int:
        """Decode the ordinary messages lying whole in `buf` from `pos` in one loop (the common
        case, once per chunk); stop at anything else, which `_step` handles. Returns the new pos."""
        size, base, limit = len(buf), self._buf_offset, self.max_message_size
        with memoryview(buf) as view:
            while size - pos >= MESSAGE_HEADER_SIZE and buf[pos] != _R:
                kind, length = _MESSAGE_HEADER.unpack_from(buf, pos)
                start = pos + MESSAGE_HEADER_SIZE
                end = start + length
                if kind > MessageKind.BLUEPRINT_ACTIVATION or length > limit or end > size:
                    break
                self._msg_offset, self._kind, self._length = base + pos, kind, length
                event = self._decode_message(bytes(view[start:end]))
                pos = end
                if event is not None:
                    events.append(event)
                if self._state is not _State.MESSAGE_HEADER:
                    break
        return pos

    def _raise_pending(self) -> None:
        if self._error is not None:
            raise self._error

    def payload_target(self) -> memoryview | None:
        """While a large message is being read: room for its next bytes, so a file reader can
        `readinto` it directly, then call `payload_filled`. Release the view before the next call."""
        if self._large is None:
            return None
        have = len(self._large)
        self._large += bytes(min(self._length - have, LARGE_STEP))  # grows only as data arrives
        return memoryview(self._large)[have:]

    def payload_filled(self, count: int) -> list[Event]:
        """`count` bytes were written at the start of the last `payload_target()`."""
        assert self._large is not None
        del self._large[self._filled + count :]
        events: list[Event] = []
        self._advance_large(count, events)
        return events

    def _fill_large(self, data: bytes | bytearray | memoryview, events: list[Event]) -> int:
        assert self._large is not None
        count = min(len(data), self._length - self._filled)
        self._large += memoryview(data)[:count]
        self._advance_large(count, events)
        return count

    def _advance_large(self, count: int, events: list[Event]) -> None:
        assert self._large is not None
        self._filled += count
        self._buf_offset += count
        if self._filled < self._length:
            return
        raw, self._large = self._large, None
        self._state = _State.MESSAGE_HEADER
        try:
            event = self._decode_message(raw)
        except errors.RrdError as exc:
            self._error = exc
            return
        if event is not None:
            events.append(event)

    def finish(self) -> list[Event]:
        """Call at end of input: returns nothing more, or raises if the input ended badly."""
        self._raise_pending()
        events: list[Event] = []
        remaining = len(self._buf)
        if self._state is _State.STREAM_HEADER:
            if self._streams == 0 and remaining == 0:
                raise errors.NotAnRrdError("input is empty", self._buf_offset)
            if remaining:
                head = bytes(self._buf[:4])
                if self._streams == 0 and not (FOURCC.startswith(head) or looks_like_stream_header(head)):
                    raise errors.NotAnRrdError(f"expected magic b'RRF2', found {head!r}", self._buf_offset)
                if self._streams == 0 or looks_like_stream_header(head):
                    raise errors.TruncatedError(
                        f"stream header needs {STREAM_HEADER_SIZE} bytes, only {remaining} remain",
                        self._buf_offset,
                    )
                raise errors.FooterError(f"{remaining} unexpected bytes after the end of the stream", self._buf_offset)
        elif self._state is _State.MESSAGE_HEADER:
            if remaining:
                raise errors.TruncatedError(
                    f"message header needs {MESSAGE_HEADER_SIZE} bytes, only {remaining} remain",
                    self._buf_offset,
                )
        elif self._state is _State.PAYLOAD:
            have = self._filled if self._large is not None else remaining
            raise errors.TruncatedError(
                f"{MessageKind(self._kind).name} message declares {self._length} bytes, only {have} remain",
                self._msg_offset,
            )
        elif remaining or self._footer_entries:  # AFTER_END: a partial stream footer
            start = self._footer_entries[0][0] if self._footer_entries else self._buf_offset
            raise errors.TruncatedError("stream footer cut off", start)
        return events

    # --- state machine -------------------------------------------------------------------

    def _step(self, buf: bytearray, pos: int, events: list[Event]) -> int | None:
        """Consume one unit at `pos` if complete; return the bytes consumed (None = need more)."""
        available = len(buf) - pos
        here = self._buf_offset + pos
        state = self._state
        if state is _State.MESSAGE_HEADER:
            if available < MESSAGE_HEADER_SIZE:
                # A new stream header may follow without an End message (concatenation).
                if available >= 4 and looks_like_stream_header(bytes(buf[pos : pos + 4])):
                    self._state = _State.STREAM_HEADER
                    return self._step(buf, pos, events)
                return None
            # A message header starts with its kind (0-3); b"R" may start a concatenated stream.
            if buf[pos] == _R and looks_like_stream_header(bytes(buf[pos : pos + 4])):
                self._state = _State.STREAM_HEADER
                return self._step(buf, pos, events)
            kind, length = decode_message_header(buf, pos)
            if kind > MessageKind.BLUEPRINT_ACTIVATION:
                raise errors.UnknownMessageKindError(f"kind {kind}, expected 0 to 3", here)
            if length > self.max_message_size:
                raise errors.MessageTooLargeError(
                    f"{MessageKind(kind).name} message declares {length} bytes, over the limit of "
                    f"{self.max_message_size} (raise the limit, FLEET_MAX_MESSAGE_SIZE, if this is expected)",
                    here,
                )
            self._msg_offset, self._kind, self._length = here, kind, length
            self._state = _State.PAYLOAD
            return MESSAGE_HEADER_SIZE
        if state is _State.PAYLOAD:
            if self._large is not None:
                return None
            if available < self._length:
                if self._length >= LARGE_MESSAGE:
                    # Large messages get their own buffer, filled in place (not re-copied), which
                    # grows with the data received, never to the declared size up front.
                    with memoryview(buf) as view:
                        self._large = bytearray(view[pos : pos + available])
                    self._filled = available
                    return available
                return None
            with memoryview(buf) as view:  # one copy, and the view is released before resizing
                raw = bytes(view[pos : pos + self._length])
            self._state = _State.MESSAGE_HEADER
            event = self._decode_message(raw)
            if event is not None:
                events.append(event)
            return self._length
        if state is _State.STREAM_HEADER:
            if available < STREAM_HEADER_SIZE:
                if available >= 4 and not looks_like_stream_header(bytes(buf[pos : pos + 4])):
                    decode_stream_header(bytes(buf[pos : pos + 4]).ljust(STREAM_HEADER_SIZE, b"\0"), here)
                return None
            header = decode_stream_header(bytes(buf[pos : pos + STREAM_HEADER_SIZE]), here)
            events.append(StreamStart(here, self._streams, header))
            self._streams += 1
            self._stream_offset = here
            self._state = _State.MESSAGE_HEADER
            return STREAM_HEADER_SIZE
        return self._step_after_end(buf, pos, available, here, events)

    def _step_after_end(self, buf: bytearray, pos: int, available: int, here: int, events: list[Event]) -> int | None:
        assert self._end is not None
        end_start, end_len, end_payload = self._end
        if available < 8:  # "RRF2" may begin a new stream or the b"RRF2FOOT" marker: wait
            return None
        head = bytes(buf[pos : pos + 8])
        if head == FOOTER_MAGIC:
            if available < FOOTER_FIXED_SIZE:
                return None
            count = int.from_bytes(buf[pos + 8 : pos + 12], "little")
            if count != len(self._footer_entries):
                raise errors.FooterError(
                    f"stream footer says {count} entries, {len(self._footer_entries)} precede it", here
                )
            # The trailer is reported once whole, so a cut one reads as truncated, not as present.
            events.extend(StreamFooter(*entry) for entry in self._footer_entries)
            self._footer_entries.clear()
            self._state = _State.STREAM_HEADER
            return FOOTER_FIXED_SIZE
        if int.from_bytes(head, "little") != end_start:
            if looks_like_stream_header(head):
                self._state = _State.STREAM_HEADER
                return self._step(buf, pos, events)
            raise errors.FooterError(
                f"expected a stream footer pointing at byte {end_start} of the stream, "
                f"or a new stream; found {head.hex()}",
                here,
            )
        if available < FOOTER_ENTRY_SIZE:
            return None
        start, length, crc = decode_footer_entry(buf, pos)
        if length != end_len:
            raise errors.FooterError(f"stream footer length {length} != End payload length {end_len}", here)
        if crc != footer_crc(end_payload):
            raise errors.FooterError(
                f"stream footer CRC {crc:08x} does not match the End payload ({footer_crc(end_payload):08x})",
                here,
            )
        self._footer_entries.append((here, self._streams - 1, start, length, crc))
        return FOOTER_ENTRY_SIZE

    def _decode_message(self, raw: Buffer) -> Event | None:
        offset, kind = self._msg_offset, self._kind
        message = self._store_ids.complete(
            decode_message(
                kind, raw, offset, self._stream_offset, self._streams - 1, max_chunk_bytes=self.max_chunk_bytes
            )
        )
        if isinstance(message, EndMessage):
            self._end = (offset + MESSAGE_HEADER_SIZE - self._stream_offset, len(message.raw), bytes(message.raw))
            self._state = _State.AFTER_END
        return message


def decode_message(
    kind: int,
    raw: Buffer,
    offset: int = 0,
    stream_offset: int = 0,
    stream_index: int = 0,
    *,
    max_chunk_bytes: int | None = None,
) -> Message:
    """A typed message from its kind and protobuf bytes (from an RRD frame or a gRPC LogMsg).
    An Arrow message declaring a chunk over `max_chunk_bytes` (default: the process's
    FLEET_MAX_CHUNK_BYTES) is refused here, before its payload is decompressed."""
    where = (offset, stream_offset, stream_index)
    try:
        if kind == MessageKind.ARROW_MSG:
            message = _arrow_message(raw, *where)
            check_chunk_size(message, limits.max_chunk_bytes() if max_chunk_bytes is None else max_chunk_bytes)
            return message
        raw = bytes(raw)  # no copy unless a rare large non-chunk message came in a bytearray
        if kind == MessageKind.SET_STORE_INFO:
            return _store_info_message(raw, *where)
        if kind == MessageKind.BLUEPRINT_ACTIVATION:
            pb = log_msg_pb2.BlueprintActivationCommand.FromString(raw)
            return BlueprintActivationMessage(
                *where, raw, StoreId.from_proto(pb.blueprint_id), pb.make_active, pb.make_default
            )
        if kind == MessageKind.END:
            return EndMessage(*where, raw, log_msg_pb2.RrdFooter.FromString(raw) if raw else None)
    except DecodeError as exc:
        raise errors.ProtobufError(f"{MessageKind(kind).name} payload: {exc}", offset) from exc
    raise errors.UnknownMessageKindError(f"kind {kind}, expected 0 to 3", offset)


def _store_info_message(raw: bytes, offset: int, stream_offset: int, stream_index: int) -> StoreInfoMessage:
    pb = log_msg_pb2.SetStoreInfo.FromString(raw)
    info = pb.info
    if not info.HasField("store_id"):
        raise errors.ProtobufError("SetStoreInfo has no store_id", offset)
    store_id = StoreId.from_proto(info.store_id)
    if not store_id.application_id and info.HasField("application_id"):
        store_id = StoreId(store_id.kind, info.application_id.id, store_id.recording_id)
    version = RerunVersion.from_bits(info.store_version.crate_version_bits) if info.HasField("store_version") else None
    return StoreInfoMessage(offset, stream_offset, stream_index, raw, store_id, version, _source(info))


def _source(info: log_msg_pb2.StoreInfo) -> str:
    source = info.store_source
    name = log_msg_pb2.StoreSourceKind.Name(source.kind) if source.kind in (0, 1, 2, 3, 4, 5, 6) else "?"
    label = name.removeprefix("STORE_SOURCE_KIND_").lower()
    if source.kind == log_msg_pb2.STORE_SOURCE_KIND_PYTHON_SDK and source.extra.payload:
        try:
            py = log_msg_pb2.PythonVersion.FromString(source.extra.payload)
            label += f" (python {py.major}.{py.minor}.{py.patch}{py.suffix})"
        except DecodeError:
            pass
    return label


def _arrow_message(raw: Buffer, offset: int, stream_offset: int, stream_index: int) -> ArrowMessage:
    payload: bytes | memoryview
    if len(raw) >= LARGE_MESSAGE:
        # Parse everything but the payload, which stays a view into `raw` (never copied).
        found = protowire.last_field(raw, _ARROW_PAYLOAD_FIELD, offset)
        start, value, end = found if found is not None else (len(raw), len(raw), len(raw))
        pb = log_msg_pb2.ArrowMsg.FromString(bytes(raw[:start]) + bytes(raw[end:]))
        payload = memoryview(raw)[value:end]
    else:
        pb = log_msg_pb2.ArrowMsg.FromString(bytes(raw))  # small messages arrive as bytes: no copy
        payload = pb.payload
    compression = _COMPRESSIONS.get(pb.compression)
    if compression is None:
        raise errors.UnknownCompressionError(
            f"ArrowMsg compression {pb.compression}, expected 1 (none) or 2 (LZ4)", offset
        )
    if pb.encoding not in (log_msg_pb2.ENCODING_UNSPECIFIED, log_msg_pb2.ENCODING_ARROW_IPC):
        raise errors.ProtobufError(f"ArrowMsg encoding {pb.encoding}, expected 1 (Arrow IPC)", offset)
    return ArrowMessage(
        offset,
        stream_offset,
        stream_index,
        raw,
        store_id=_store_id(pb.store_id),
        chunk_id=tuid_bytes(pb.chunk_id) if pb.HasField("chunk_id") else None,
        is_static=pb.is_static if pb.HasField("is_static") else None,
        compression=compression,
        uncompressed_size=pb.uncompressed_size,
        payload=payload,
    )


def check_chunk_size(msg: ArrowMessage, limit: int) -> None:
    """MessageTooLargeError if the chunk in `msg` would take more than `limit` bytes once decompressed."""
    size = msg.uncompressed_size if msg.compression == Compression.LZ4 else len(msg.payload)
    if size > limit:
        raise errors.MessageTooLargeError(
            f"chunk declares {size} bytes uncompressed ({len(msg.payload)} compressed), over the limit of "
            f"{limit} (raise FLEET_MAX_CHUNK_BYTES if chunks this large are expected)",
            msg.offset,
        )


_COMPRESSIONS = {int(c): c for c in Compression}
_STORE_IDS: dict[tuple[int, str, str], StoreId] = {}


def _store_id(pb: common_pb2.StoreId) -> StoreId:
    """StoreId objects are shared: a stream repeats the same few on every chunk."""
    key = (pb.kind, pb.application_id.id, pb.recording_id)
    store_id = _STORE_IDS.get(key)
    if store_id is None:
        if len(_STORE_IDS) > 10_000:
            _STORE_IDS.clear()
        store_id = _STORE_IDS[key] = StoreId.from_proto(pb)
    return store_id


_ARROW_PAYLOAD_FIELD = 5


def iter_events(
    source: BinaryIO | str | os.PathLike[str],
    *,
    max_message_size: int = DEFAULT_MAX_MESSAGE_SIZE,
    read_size: int = READ_SIZE,
    max_chunk_bytes: int | None = None,
) -> Iterator[Event]:
    """Every event of a file or binary stream, read in pieces of `read_size` bytes.

    Raises the codec error at the end (after yielding everything before it) if the input is bad.
    """
    if isinstance(source, (str, os.PathLike)):
        with open(source, "rb") as fh:
            yield from iter_events(
                fh, max_message_size=max_message_size, read_size=read_size, max_chunk_bytes=max_chunk_bytes
            )
        return
    decoder = RrdDecoder(max_message_size=max_message_size, max_chunk_bytes=max_chunk_bytes)
    can_readinto = hasattr(source, "readinto")
    while True:
        target = decoder.payload_target() if can_readinto else None
        if target is not None:
            with target:  # large messages are read straight into their buffer
                count = source.readinto(target) or 0  # type: ignore[attr-defined]
            events = decoder.payload_filled(count)
            if not count:
                break
            yield from events
            continue
        data = source.read(read_size)
        if not data:
            break
        yield from decoder.feed(data)
    yield from decoder.finish()
