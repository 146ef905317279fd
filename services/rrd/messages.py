"""Typed RRD messages as the decoder yields them, each with its position in the input.

A message keeps `raw`, the exact protobuf bytes it was read from, so writers pass it through
untouched; an Arrow message's `payload` is never decompressed or re-encoded here.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from services.rrd.frames import MESSAGE_HEADER_SIZE, MessageKind, RerunVersion, StreamHeader
from services.rrd.pb import common_pb2, log_msg_pb2

Buffer = bytes | bytearray | memoryview  # message bytes: a copy, a read buffer, or a view into one


class StoreKind(enum.IntEnum):
    UNSPECIFIED = 0
    RECORDING = 1
    BLUEPRINT = 2


class Compression(enum.IntEnum):
    """Per-message payload compression (the protobuf enum, not the stream-header byte)."""

    UNSPECIFIED = 0
    NONE = 1
    LZ4 = 2


@dataclass(frozen=True, slots=True)
class StoreId:
    kind: StoreKind
    application_id: str
    recording_id: str

    @classmethod
    def from_proto(cls, pb: common_pb2.StoreId) -> StoreId:
        return cls(
            StoreKind(pb.kind) if pb.kind in (1, 2) else StoreKind.UNSPECIFIED, pb.application_id.id, pb.recording_id
        )

    def to_proto(self) -> common_pb2.StoreId:
        return common_pb2.StoreId(
            kind=int(self.kind),  # type: ignore[arg-type]
            recording_id=self.recording_id,
            application_id=common_pb2.ApplicationId(id=self.application_id),
        )

    @property
    def is_blueprint(self) -> bool:
        return self.kind == StoreKind.BLUEPRINT

    def __str__(self) -> str:
        return f"{self.kind.name.lower()}:{self.application_id}/{self.recording_id}"


_TUID = struct.Struct(">QQ")


def tuid_bytes(pb: common_pb2.Tuid) -> bytes:
    """A TUID as Rerun stores it in Arrow: time_ns big-endian then inc big-endian (16 bytes)."""
    return _TUID.pack(pb.time_ns, pb.inc)


def tuid_str(raw: bytes) -> str:
    """Rerun's display form of a TUID: time_ns as 16 upper-case hex digits, inc as 16 lower-case."""
    return raw[:8].hex().upper() + raw[8:].hex()


def chunk_id_str(raw: bytes) -> str:
    return "chunk_" + tuid_str(raw)


def tuid_proto(raw: bytes) -> common_pb2.Tuid:
    return common_pb2.Tuid(time_ns=int.from_bytes(raw[:8], "big"), inc=int.from_bytes(raw[8:], "big"))


@dataclass(slots=True)
class Located:
    """Where a message sits: `offset` of its 16-byte header in the whole input, and the offset of
    the stream (header) it belongs to; RRD footers count positions from the stream start."""

    offset: int
    stream_offset: int
    stream_index: int

    @property
    def payload_offset(self) -> int:
        return self.offset + MESSAGE_HEADER_SIZE

    @property
    def stream_payload_offset(self) -> int:
        return self.payload_offset - self.stream_offset


@dataclass(slots=True)
class StreamStart:
    """A stream header: the first thing in a file, and again at each concatenated stream."""

    offset: int
    stream_index: int
    header: StreamHeader

    @property
    def version(self) -> RerunVersion:
        return self.header.version


@dataclass(slots=True)
class StoreInfoMessage(Located):
    raw: Buffer
    store_id: StoreId
    sdk_version: RerunVersion | None
    source: str
    kind: MessageKind = MessageKind.SET_STORE_INFO


@dataclass(slots=True)
class ArrowMessage(Located):
    raw: Buffer  # large messages keep the buffer they were read into; gRPC ones are views
    store_id: StoreId
    chunk_id: bytes | None
    is_static: bool | None
    compression: Compression
    uncompressed_size: int
    payload: bytes | memoryview  # a view into `raw` for large messages
    kind: MessageKind = MessageKind.ARROW_MSG

    @property
    def size(self) -> int:
        """Bytes of the protobuf message (what the RRD manifest calls chunk_byte_size)."""
        return len(self.raw)


@dataclass(slots=True)
class BlueprintActivationMessage(Located):
    raw: Buffer
    blueprint_id: StoreId
    make_active: bool
    make_default: bool
    kind: MessageKind = MessageKind.BLUEPRINT_ACTIVATION


@dataclass(slots=True)
class EndMessage(Located):
    """End of a stream; `footer` is the parsed RrdFooter payload (None when empty)."""

    raw: Buffer
    footer: log_msg_pb2.RrdFooter | None
    kind: MessageKind = MessageKind.END


@dataclass(slots=True)
class StreamFooter:
    """The trailer after an End message, pointing back at the footer payload (stream-relative)."""

    offset: int
    stream_index: int
    footer_start: int
    footer_length: int
    crc: int


Message = StoreInfoMessage | ArrowMessage | BlueprintActivationMessage | EndMessage
Event = StreamStart | Message | StreamFooter
