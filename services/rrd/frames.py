"""Byte-level layout of RRD streams: the stream header, message headers and the stream footer.

Layout (all integers little-endian), see docs/rrd-codec.md:
  stream header   12 B: b"RRF2", version [major, minor, patch, meta], compression, serializer, 0, 0
  message header  16 B: u64 kind, u64 len; then `len` bytes of protobuf
  End message     kind 0; its payload is an `RrdFooter` protobuf (possibly empty)
  stream footer   per entry: u64 footer_start, u64 footer_len, u32 xxh32(footer, 7850921);
                  then b"RRF2FOOT" and u32 entry count (the fixed part always ends the stream)
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

import xxhash

from services.rrd import errors

FOURCC = b"RRF2"
OLD_FOURCCS = (b"RRF0", b"RRF1")
STREAM_HEADER_SIZE = 12
MESSAGE_HEADER_SIZE = 16
FOOTER_MAGIC = b"RRF2FOOT"
FOOTER_ENTRY_SIZE = 20
FOOTER_FIXED_SIZE = 12
FOOTER_CRC_SEED = 7850921  # "RERUN" in base 26

# Stream-header compression byte (0/1). Not the protobuf `Compression` enum (1 = NONE, 2 = LZ4).
HEADER_COMPRESSION_OFF = 0
HEADER_COMPRESSION_LZ4 = 1
SERIALIZER_PROTOBUF = 2
_SERIALIZER_MSGPACK = 1

# Rerun refuses streams written before 0.23 (the protobuf era).
OLDEST_SUPPORTED = (0, 23)
# Rerun itself cannot convert recordings this old (`rerun rrd migrate` refuses them): the robot
# has to record with a newer SDK.
UPGRADE_HINT = (
    "the oldest supported rerun-sdk is 0.23: upgrade rerun-sdk on the robot (pip install -U rerun-sdk) and record again"
)

_MESSAGE_HEADER = struct.Struct("<QQ")
_FOOTER_ENTRY = struct.Struct("<QQI")


class MessageKind(enum.IntEnum):
    END = 0
    SET_STORE_INFO = 1
    ARROW_MSG = 2
    BLUEPRINT_ACTIVATION = 3


@dataclass(frozen=True, order=True)
class RerunVersion:
    """A Rerun crate version as stored in stream headers and `StoreVersion.crate_version_bits`."""

    major: int
    minor: int
    patch: int
    meta: int = 0

    @classmethod
    def from_bytes(cls, raw: bytes) -> RerunVersion:
        return cls(raw[0], raw[1], raw[2], raw[3])

    @classmethod
    def from_bits(cls, bits: int) -> RerunVersion:
        return cls.from_bytes((bits & 0xFFFFFFFF).to_bytes(4, "little"))

    def to_bytes(self) -> bytes:
        return bytes((self.major, self.minor, self.patch, self.meta))

    def __str__(self) -> str:
        text = f"{self.major}.{self.minor}.{self.patch}"
        kind, n = self.meta >> 6, self.meta & 0x3F
        if kind == 0b10:
            text += f"-alpha.{n}"
        elif kind == 0b11:
            text += f"-alpha.{n}+dev"
        elif kind == 0b01:
            text += f"-rc.{n}"
        return text


DEFAULT_VERSION = RerunVersion(0, 41, 0)  # for a stream whose writer named no version


@dataclass(frozen=True)
class StreamHeader:
    version: RerunVersion
    compression: int = HEADER_COMPRESSION_LZ4
    serializer: int = SERIALIZER_PROTOBUF

    def encode(self) -> bytes:
        return FOURCC + self.version.to_bytes() + bytes((self.compression, self.serializer, 0, 0))


def looks_like_stream_header(prefix: bytes) -> bool:
    """True if `prefix` (>= 4 bytes) starts a stream header of any RRF generation."""
    return prefix[:3] == b"RRF" and prefix[3:4] in (b"0", b"1", b"2")


def decode_stream_header(raw: bytes, offset: int) -> StreamHeader:
    """Parse 12 header bytes found at absolute `offset`; raise the specific error if invalid."""
    fourcc = raw[:4]
    if fourcc in OLD_FOURCCS:
        raise errors.UnsupportedVersionError(
            f"{fourcc.decode()} stream written by a Rerun older than 0.23; {UPGRADE_HINT}", offset
        )
    if fourcc != FOURCC:
        raise errors.NotAnRrdError(f"expected magic b'RRF2', found {fourcc!r}", offset)
    version = RerunVersion.from_bytes(raw[4:8])
    if version != RerunVersion(0, 0, 0, 0) and (version.major, version.minor) < OLDEST_SUPPORTED:
        raise errors.UnsupportedVersionError(f"written by rerun-sdk {version}; {UPGRADE_HINT}", offset + 4)
    compression, serializer = raw[8], raw[9]
    if compression not in (HEADER_COMPRESSION_OFF, HEADER_COMPRESSION_LZ4):
        raise errors.UnknownCompressionError(
            f"stream compression byte is {compression}, expected 0 (off) or 1 (LZ4)", offset + 8
        )
    if serializer == _SERIALIZER_MSGPACK:
        raise errors.UnknownSerializerError(
            "MsgPack serializer was removed from Rerun; only protobuf (2) is read", offset + 9
        )
    if serializer != SERIALIZER_PROTOBUF:
        raise errors.UnknownSerializerError(f"serializer byte is {serializer}, expected 2 (protobuf)", offset + 9)
    if raw[10:12] != b"\0\0":
        raise errors.ReservedBytesError(f"bytes 10-11 are {raw[10:12].hex()}, expected 0000", offset + 10)
    return StreamHeader(version, compression, serializer)


def encode_message_header(kind: int, length: int) -> bytes:
    return _MESSAGE_HEADER.pack(kind, length)


def decode_message_header(raw: bytes | bytearray | memoryview, pos: int = 0) -> tuple[int, int]:
    kind, length = _MESSAGE_HEADER.unpack_from(raw, pos)
    return int(kind), int(length)


def footer_crc(footer_payload: bytes) -> int:
    return xxhash.xxh32_intdigest(footer_payload, seed=FOOTER_CRC_SEED)


def encode_stream_footer(footer_start: int, footer_payload: bytes) -> bytes:
    """The 32-byte trailer for one End-message payload starting at `footer_start` (stream-relative)."""
    entry = _FOOTER_ENTRY.pack(footer_start, len(footer_payload), footer_crc(footer_payload))
    return entry + FOOTER_MAGIC + struct.pack("<I", 1)


def decode_footer_entry(raw: bytes | bytearray | memoryview, pos: int = 0) -> tuple[int, int, int]:
    start, length, crc = _FOOTER_ENTRY.unpack_from(raw, pos)
    return int(start), int(length), int(crc)
