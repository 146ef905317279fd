"""Just enough of the protobuf wire format to find fields without parsing (or copying) values:
used to keep large chunk payloads in place and to unwrap gRPC `LogMsg`s byte for byte."""

from __future__ import annotations

from collections.abc import Iterator

from services.rrd import errors

Buffer = bytes | bytearray | memoryview


def varint(raw: Buffer, pos: int, offset: int) -> tuple[int, int]:
    """(value, next position); `offset` only places errors."""
    result = shift = 0
    while True:
        if pos >= len(raw) or shift > 63:
            raise errors.ProtobufError("bad varint", offset)
        byte = raw[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result, pos
        shift += 7


def fields(raw: Buffer, offset: int = 0) -> Iterator[tuple[int, int, int, int]]:
    """(field number, tag start, value start, value end) of each top-level field; for a
    length-delimited field the value is its bytes, for others its encoding."""
    pos = 0
    while pos < len(raw):
        tag_start = pos
        key, pos = varint(raw, pos, offset)
        wire, number = key & 7, key >> 3
        start = pos
        if wire == 0:
            _, pos = varint(raw, pos, offset)
        elif wire == 1:
            pos += 8
        elif wire == 5:
            pos += 4
        elif wire == 2:
            length, start = varint(raw, pos, offset)
            pos = start + length
        else:
            raise errors.ProtobufError(f"wire type {wire} in field {number}", offset)
        if pos > len(raw):
            raise errors.ProtobufError(f"field {number} runs past the end of the message", offset)
        yield number, tag_start, start, pos


def last_field(raw: Buffer, number: int, offset: int = 0) -> tuple[int, int, int] | None:
    """(tag start, value start, value end) of the last occurrence of field `number` (protobuf:
    the last one wins), or None."""
    found = None
    for field, tag_start, start, end in fields(raw, offset):
        if field == number:
            found = (tag_start, start, end)
    return found


def encode_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def log_msg_envelope(kind: int, raw: Buffer) -> bytes:
    """`{ LogMsg log_msg = 1 }` around a message's own bytes: both a serialized WriteMessagesRequest
    and a ReadMessagesResponse (LogMsg's oneof field numbers are the message kinds 1-3). Nothing is
    re-encoded."""
    inner = bytes([(kind << 3) | 2]) + encode_varint(len(raw)) + bytes(raw)
    return bytes([(1 << 3) | 2]) + encode_varint(len(inner)) + inner
