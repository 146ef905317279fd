"""Unwrapping a WriteMessagesRequest: the SDK's form (log_msg alone, one message in it) is read in a
few steps; any other form takes the field walk, and both say what protobuf says."""

from __future__ import annotations

import pytest

from services.ingest.requests import unwrap
from services.rrd import errors
from services.rrd.pb import common_pb2, log_msg_pb2, sdk_comms_pb2


def _arrow() -> log_msg_pb2.ArrowMsg:
    store = common_pb2.StoreId(kind=1, recording_id="rec", application_id=common_pb2.ApplicationId(id="app"))  # type: ignore[arg-type]
    return log_msg_pb2.ArrowMsg(store_id=store, compression=2, uncompressed_size=300, payload=b"x" * 200)  # type: ignore[arg-type]


def _varint(value: int) -> bytes:
    out = bytearray()
    while value >= 0x80:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    return bytes(out + bytes([value]))


def _request(**log_msg: object) -> bytes:
    return sdk_comms_pb2.WriteMessagesRequest(log_msg=log_msg_pb2.LogMsg(**log_msg)).SerializeToString()  # type: ignore[arg-type]


@pytest.mark.parametrize("payload", [200, 5_000, 300_000])  # lengths of one, two and three varint bytes
def test_the_sdks_form(payload: int) -> None:
    arrow = _arrow()
    arrow.payload = b"y" * payload
    kind, raw = unwrap(_request(arrow_msg=arrow), 0)
    assert (kind, bytes(raw)) == (2, arrow.SerializeToString())
    info = log_msg_pb2.SetStoreInfo(row_id=common_pb2.Tuid(time_ns=1, inc=2))
    kind, raw = unwrap(_request(set_store_info=info), 0)
    assert (kind, bytes(raw)) == (1, info.SerializeToString())


def test_other_forms_read_as_protobuf_reads_them() -> None:
    arrow = _arrow()
    plain = _request(arrow_msg=arrow)
    unknown_after = plain + b"\x10\x01"  # a field WriteMessagesRequest does not have (skipped)
    log_msg = log_msg_pb2.LogMsg(arrow_msg=arrow).SerializeToString()
    unknown_inside = b"\x0a" + _varint(len(log_msg) + 2) + b"\x28\x07" + log_msg  # LogMsg field 5 first
    for request in (unknown_after, unknown_inside):
        parsed = sdk_comms_pb2.WriteMessagesRequest.FromString(request)
        kind, raw = unwrap(request, 0)
        assert kind == 2 and log_msg_pb2.ArrowMsg.FromString(bytes(raw)) == parsed.log_msg.arrow_msg


@pytest.mark.parametrize("request_bytes", [b"", b"\x0a\x00", b"\x0a\x05\x12\x09abc", b"\x0a\x02\x12\x09"])
def test_malformed_requests_are_refused(request_bytes: bytes) -> None:
    with pytest.raises(errors.ProtobufError):
        unwrap(request_bytes, 7)
