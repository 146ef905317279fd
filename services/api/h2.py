"""HTTP/2 as the gRPC port's front reads it (RFC 9113): frame layout, and request header blocks.

Both halves of the front use this: `grpc_front` reads a connection's first request (and rewrites
headers some clients get wrong), `h2_writes` serves whole WriteMessages connections.
"""

from __future__ import annotations

import base64
import binascii
import struct
from dataclasses import dataclass, field

from hpack import Decoder, HeaderTuple
from hpack.exceptions import HPACKError

PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"
FRAME_HEAD = 9  # a 24-bit length, the type, the flags, then a 31-bit stream id
STREAM_ID = struct.Struct(">I")  # a stream id, a window increment, an error code: all 32 bits

# Frame types.
DATA, HEADERS, RST_STREAM, SETTINGS, PUSH_PROMISE, PING, GOAWAY, WINDOW_UPDATE, CONTINUATION = (
    0x0,
    0x1,
    0x3,
    0x4,
    0x5,
    0x6,
    0x7,
    0x8,
    0x9,
)
# Flags (ACK is END_STREAM's bit, on SETTINGS and PING).
END_STREAM, ACK, END_HEADERS, PADDED, PRIORITY = 0x1, 0x1, 0x4, 0x8, 0x20
# Error codes.
NO_ERROR, PROTOCOL_ERROR, FLOW_CONTROL_ERROR, FRAME_SIZE_ERROR, REFUSED_STREAM, CANCEL, COMPRESSION_ERROR = (
    0x0,
    0x1,
    0x3,
    0x6,
    0x7,
    0x8,
    0x9,
)
# Settings.
SETTINGS_HEADER_TABLE_SIZE, SETTINGS_MAX_CONCURRENT_STREAMS, SETTINGS_INITIAL_WINDOW_SIZE = 0x1, 0x3, 0x4
SETTINGS_MAX_FRAME_SIZE, SETTINGS_MAX_HEADER_LIST_SIZE = 0x5, 0x6
# Every HTTP/2 peer accepts frames of this size (the default SETTINGS_MAX_FRAME_SIZE).
MIN_MAX_FRAME = 16384
# The largest header table a client may make this end keep per connection.
DECODER_TABLE_LIMIT = 65536


class ProtocolError(Exception):
    """The client broke HTTP/2; the connection ends (with GOAWAY and `code`, where one is sent)."""

    def __init__(self, reason: str, code: int = PROTOCOL_ERROR) -> None:
        super().__init__(reason)
        self.code = code


def frame(kind: int, flags: int, stream: int, payload: bytes = b"") -> bytes:
    return len(payload).to_bytes(3, "big") + bytes((kind, flags)) + STREAM_ID.pack(stream) + payload


def goaway(last_stream: int, code: int, reason: bytes = b"") -> bytes:
    return frame(GOAWAY, 0, 0, STREAM_ID.pack(last_stream) + STREAM_ID.pack(code) + reason)


def rst_stream(stream: int, code: int) -> bytes:
    return frame(RST_STREAM, 0, stream, STREAM_ID.pack(code))


def window_update(stream: int, increment: int) -> bytes:
    return frame(WINDOW_UPDATE, 0, stream, STREAM_ID.pack(increment))


def header_frames(stream: int, block: bytes, flags: int, priority: bytes = b"") -> bytes:
    """A header block as a HEADERS frame and CONTINUATIONs of at most MIN_MAX_FRAME bytes each;
    `flags`: END_STREAM or not (END_HEADERS and PRIORITY are set here)."""
    first_room = MIN_MAX_FRAME - len(priority)
    pieces = [block[:first_room]] + [block[i : i + MIN_MAX_FRAME] for i in range(first_room, len(block), MIN_MAX_FRAME)]
    flags = (flags & END_STREAM) | (PRIORITY if priority else 0)
    last = len(pieces) - 1
    out = [frame(HEADERS, flags | (END_HEADERS if last == 0 else 0), stream, priority + pieces[0])]
    out += [frame(CONTINUATION, END_HEADERS if i == last else 0, stream, p) for i, p in enumerate(pieces[1:], 1)]
    return b"".join(out)


def data_frames(stream: int, data: bytes) -> bytes:
    """`data` as DATA frames of at most MIN_MAX_FRAME bytes (the stream stays open)."""
    return b"".join(frame(DATA, 0, stream, data[i : i + MIN_MAX_FRAME]) for i in range(0, len(data), MIN_MAX_FRAME))


def binary_value(value: bytes) -> bytes:
    """A `-bin` metadata value as gRPC sends it, decoded: base64 (padding optional), or raw after
    a 0 byte (C-core's "true binary", which the gRPC server's SETTINGS allow its clients)."""
    if value[:1] == b"\0":
        return value[1:]
    try:
        return base64.b64decode(value + b"=" * (-len(value) % 4))
    except binascii.Error:
        return value  # not base64: as it came (a handler names what it cannot read)


def metadata_value(name: str, value: str | bytes) -> bytes:
    """A metadata value as gRPC sends it: `-bin` values base64-encoded, others as ASCII."""
    if name.endswith("-bin"):
        raw = value.encode() if isinstance(value, str) else value
        return base64.b64encode(raw).rstrip(b"=")
    return value.encode() if isinstance(value, str) else value


def frame_head(data: bytes | bytearray, pos: int) -> tuple[int, int, int, int]:
    """The length, type, flags and stream id of the frame whose header starts at `pos`."""
    length = int.from_bytes(data[pos : pos + 3], "big")
    stream = STREAM_ID.unpack_from(data, pos + 5)[0] & 0x7FFFFFFF
    return length, data[pos + 3], data[pos + 4], stream


@dataclass
class HeaderBlock:
    """One header block, which HTTP/2 may split over a HEADERS frame and CONTINUATIONs."""

    stream: int
    flags: int  # its HEADERS frame's flags (END_STREAM among them)
    priority: bytes  # the HEADERS frame's priority fields, as sent (b"" if none)
    start: int  # where the caller says its HEADERS frame began
    fragment: bytearray = field(default_factory=bytearray)
    headers: list[HeaderTuple] = field(default_factory=list)  # decoded, once the block is whole


class HeaderBlocks:
    """Puts header blocks together from HEADERS and CONTINUATION frames and decodes them, with the
    connection's one HPACK decoder (its table lives as long as the connection)."""

    def __init__(self, limit: int) -> None:
        self.decoder = Decoder()
        self.decoder.max_allowed_table_size = DECODER_TABLE_LIMIT
        self.decoder.max_header_list_size = limit  # as announced (SETTINGS_MAX_HEADER_LIST_SIZE)
        self._limit = limit
        self._block: HeaderBlock | None = None

    @property
    def pending(self) -> bool:
        """A block was begun and not finished: HTTP/2 allows no other frame until it is."""
        return self._block is not None

    def add(self, kind: int, flags: int, stream: int, payload: bytes, start: int = 0) -> HeaderBlock | None:
        """Take a HEADERS or CONTINUATION frame; the block, decoded, once it is whole."""
        if kind == HEADERS:
            if self._block is not None:
                raise ProtocolError("a header block was interrupted by another frame")
            pos, pad = 0, 0
            if flags & PADDED:
                if not payload:
                    raise ProtocolError("a padded HEADERS frame without its pad length")
                pad, pos = payload[0], 1
            priority = payload[pos : pos + 5] if flags & PRIORITY else b""
            pos += 5 if flags & PRIORITY else 0
            if pos + pad > len(payload):
                raise ProtocolError("HEADERS padding is longer than the frame")
            self._block = HeaderBlock(stream, flags, priority, start)
            self._block.fragment += payload[pos : len(payload) - pad]
        else:
            if self._block is None or self._block.stream != stream:
                raise ProtocolError("CONTINUATION without its HEADERS")
            self._block.fragment += payload
        if len(self._block.fragment) > self._limit:
            raise ProtocolError(f"a header block over {self._limit} bytes")
        if not flags & END_HEADERS:
            return None
        block, self._block = self._block, None
        try:
            block.headers = list(self.decoder.decode(bytes(block.fragment), raw=True))
        except HPACKError as exc:
            raise ProtocolError(f"undecodable request headers ({exc})", COMPRESSION_ERROR) from None
        return block
