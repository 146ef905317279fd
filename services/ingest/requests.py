"""A serialized `WriteMessagesRequest` (what the SDK's GrpcSink sends) to the message inside it: the
inner message bytes are taken as sent (a view, never re-encoded). A request is bytes from gRPC, and
bytes or a view of a read buffer from the port's front (compiled, these types are checked)."""

from __future__ import annotations

from services.rrd import errors as rrd_errors
from services.rrd import protowire
from services.rrd.decoder import decode_message
from services.rrd.messages import Buffer, Event

_LOG_MSG_FIELD = 1  # WriteMessagesRequest.log_msg; inside, oneof fields 1-3 = message kinds 1-3
_LOG_MSG_TAGS = frozenset({(1 << 3) | 2, (2 << 3) | 2, (3 << 3) | 2})  # those fields, length-delimited


def unwrap(request: Buffer, offset: int) -> tuple[int, memoryview]:
    """(message kind, inner message bytes) of a serialized WriteMessagesRequest."""
    if len(request) > 4 and request[0] == 0x0A:  # as the SDK writes it: log_msg, one message in it
        length, start = protowire.varint(request, 1, offset)
        if start + length == len(request) and request[start] in _LOG_MSG_TAGS:
            inner, at = protowire.varint(request, start + 1, offset)
            if at + inner == len(request):
                return request[start] >> 3, memoryview(request)[at:]
    found = protowire.last_field(request, _LOG_MSG_FIELD, offset)
    if found is None:
        raise rrd_errors.ProtobufError("WriteMessagesRequest without log_msg", offset)
    log_msg = memoryview(request)[found[1] : found[2]]
    for number, _, start, end in protowire.fields(log_msg, offset):
        if number in (1, 2, 3):
            return number, log_msg[start:end]
    raise rrd_errors.ProtobufError("LogMsg holds no message", offset)


def decode_request(request: Buffer, offset: int) -> Event:
    """The message of a serialized WriteMessagesRequest at `offset` in its stream."""
    kind, raw = unwrap(request, offset)
    return decode_message(kind, raw, offset)
