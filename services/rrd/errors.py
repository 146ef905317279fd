"""Errors raised while reading or writing Rerun RRD data.

Each names the problem and the byte offset where it was found (absolute, from the start of the
input the reader was fed). The list is documented in docs/rrd-codec.md.
"""

from __future__ import annotations

from core.errors import ErrorCode, FleetError


class RrdError(FleetError):
    """Base class: the input is not valid RRD data at `offset`."""

    code = ErrorCode.INVALID_RRD
    problem = "invalid RRD data"

    def __init__(self, detail: str, offset: int) -> None:
        self.offset = offset
        self.detail = detail
        super().__init__(f"{self.problem} at byte {offset}: {detail}")


class NotAnRrdError(RrdError):
    problem = "not an RRD stream"


class UnsupportedVersionError(RrdError):
    code = ErrorCode.UNSUPPORTED_RRD_VERSION
    problem = "unsupported RRD version"


class UnknownCompressionError(RrdError):
    problem = "unknown compression"


class UnknownSerializerError(RrdError):
    problem = "unknown serializer"


class ReservedBytesError(RrdError):
    problem = "non-zero reserved bytes in stream header"


class UnknownMessageKindError(RrdError):
    problem = "unknown message kind"


class MessageTooLargeError(RrdError):
    code = ErrorCode.MESSAGE_TOO_LARGE
    problem = "message too large"


class TruncatedError(RrdError):
    problem = "truncated message"


class ProtobufError(RrdError):
    problem = "protobuf does not parse"


class DecompressionError(RrdError):
    problem = "payload does not decompress"


class NotAChunkError(RrdError):
    problem = "Arrow payload is not a Rerun chunk"


class NotArrowError(RrdError):
    """Arrow IPC data (a table a client sent) that is not a valid Arrow IPC stream."""

    problem = "invalid Arrow IPC data"


class InvalidChunkError(RrdError):
    """A chunk that Rerun itself would refuse (`rerun rrd verify`), or whose values cannot be read safely."""

    problem = "invalid chunk"


class FooterError(RrdError):
    problem = "invalid RRD footer"
