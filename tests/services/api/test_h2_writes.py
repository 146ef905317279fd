"""WriteMessages served by the front (`h2_writes`): messages however they are framed, streams and
connections ending, protocol errors, what the handler answers, metadata, and relaying."""

from __future__ import annotations

import asyncio
import base64
import itertools
import logging
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import grpc
import pytest
from hpack import Encoder

from services.api.grpc_front import Front
from services.api.h2_writes import DIRECT_BYTES, MAX_FRAME, WRITE_PATH, WriteConnection, WriteServer
from services.cluster.ownership import Owner
from services.cluster.relay import WRITE_METHOD, Relay
from tests.services.api.h2_client import (
    ACK,
    CONTINUATION,
    DATA,
    END_HEADERS,
    END_STREAM,
    HEADERS,
    INTERNAL,
    PADDED,
    PING,
    PREFACE,
    PRIORITY,
    REPLY,
    RST_STREAM,
    SETTINGS,
    TIMEOUT,
    UNIMPLEMENTED,
    Got,
    Handler,
    Reply,
    asynchronous,
    connected,
    frame,
    message,
    raw_first,
    read_all,
    request,
)

# --- messages -------------------------------------------------------------------------------------


@pytest.mark.parametrize("via_socket", [False, True])
@asynchronous
async def test_messages_arrive_byte_exact_and_in_order_however_they_are_framed(via_socket: bool):
    split, direct, big = [bytes(i * k % 251 for i in range(n)) for k, n in ((1, 3000), (3, DIRECT_BYTES), (7, 196_625))]
    bodies = [b"", b"a", b"hello" * 40, split, b"t", direct, b"b", big, b"c" * 100, big[::-1] * 13, b"end"]
    stream = b"".join(message(body) for body in bodies)
    starts = [sum(5 + len(b) for b in bodies[:i]) for i in range(len(bodies))]
    cuts = {starts[3] + 2, starts[3] + 4, starts[3] + 1000, starts[3] + 2000}  # in a prefix twice, then the body
    cuts |= {starts[5] + 1005, starts[7] + 3, starts[7] + 100_000}  # in big bodies and in a big one's prefix
    cuts |= set(range(starts[9] + 7, starts[10], 700_000))
    pieces = [stream[a:b] for a, b in itertools.pairwise(sorted({0, *cuts, len(stream)}))]
    assert max(map(len, pieces)) < MAX_FRAME - 256
    handler = Handler()
    async with connected(handler, via_socket=via_socket) as (_, client):
        for i, piece in enumerate(pieces):  # every other frame padded
            await client.data(1, piece, end=i == len(pieces) - 1, pad=(i * 37) % 256 if i % 2 else None)
        assert await client.answered(1) == 0 and b"grpc-message" not in client.trailers(1)
        assert handler.received["s1"] == bodies
        assert client.answer(1) == message(REPLY) and handler.ended["s1"] == "returned"


@asynchronous
async def test_messages_each_in_a_frame_of_its_own_arrive_in_order_between_split_ones():
    split = bytes(range(256)) * 40
    bodies = [b"", b"one", split, b"two" * 100, bytes(DIRECT_BYTES - 1), b"last"]
    handler = Handler()
    async with connected(handler, via_socket=True) as (_, client):
        for body in bodies[:2]:
            await client.data(1, message(body))
        whole = message(bodies[2])
        await client.data(1, whole[:3])  # a message cut in its prefix, then in its body
        await client.data(1, whole[3:100])
        await client.data(1, whole[100:])
        for i, body in enumerate(bodies[3:]):
            await client.data(1, message(body), end=i == len(bodies) - 4)  # the last frame ends the stream
        assert await client.answered(1) == 0
        assert handler.received["s1"] == bodies


@asynchronous
async def test_large_messages_after_the_first_are_read_from_the_socket_straight_into_their_buffers(
    monkeypatch: pytest.MonkeyPatch,
):
    read = {"direct": 0, "buffered": 0}
    original = WriteConnection.buffer_updated

    def counting(self: WriteConnection, nbytes: int) -> None:
        read["buffered" if self._direct is None else "direct"] += nbytes
        original(self, nbytes)

    monkeypatch.setattr(WriteConnection, "buffer_updated", counting)
    pattern = bytes(range(251)) * (2 * MAX_FRAME // 251)
    large = [pattern[k : k + 3 * MAX_FRAME // 2] for k in (1, 2, 3)]  # each over more than one frame
    bodies = [b"first", *large, b"small", b"end"]
    stream = b"".join(message(body) for body in bodies)
    handler = Handler()
    async with connected(handler, via_socket=True) as (_, client):
        for at in range(0, len(stream), MAX_FRAME):
            await client.data(1, stream[at : at + MAX_FRAME], end=at + MAX_FRAME >= len(stream))
        assert await client.answered(1) == 0
        assert handler.received["s1"] == bodies
    # Only the first large body (read before the connection knows large ones come) and frame heads,
    # prefixes and small messages go through the connection's buffer: the large bodies after it are
    # read straight into their own. A busy machine lets frames pile up in the socket: a buffered read
    # under way when a large body begins may take up to DIRECT_BYTES of its start.
    slack = DIRECT_BYTES * (len(large) - 1)
    assert read["direct"] >= len(large[1]) + len(large[2]) - slack
    assert read["buffered"] <= len(large[0]) + DIRECT_BYTES + slack


@asynchronous
async def test_a_header_block_in_headers_and_continuation_frames_is_served():
    block = Encoder().encode([*request("s1"), (b"x-long", b"v" * 3000)], huffman=False)
    padded = bytes([4]) + b"\x00\x00\x00\x00\x10" + block[:100] + b"\x00" * 4  # pad length, priority, pad
    first = PREFACE + frame(SETTINGS, 0, 0) + frame(HEADERS, PADDED | PRIORITY, 1, padded)
    rest = frame(CONTINUATION, 0, 1, block[100:2000]) + frame(CONTINUATION, END_HEADERS, 1, block[2000:])
    handler = Handler()
    async with connected(handler, first) as (_, client):  # the block's end comes after the hand-over
        await client.send(rest + frame(DATA, END_STREAM, 1, message(b"one") + message(b"two")))
        assert await client.answered(1) == 0 and handler.received["s1"] == [b"one", b"two"]
        assert handler.metadata["s1"]["x-long"] == "v" * 3000


@asynchronous
async def test_a_message_over_the_limit_fails_its_stream_and_the_connection_serves_the_next():
    handler = Handler()
    async with connected(handler, max_message=1000) as (_, client):
        await client.data(1, message(b"ok") + message(b"x" * 1001))
        assert await client.answered(1) == grpc.StatusCode.RESOURCE_EXHAUSTED.value[0]
        assert "FLEET_MAX_MESSAGE_SIZE" in client.details(1)
        await handler.wait(lambda: "s1" in handler.finished)
        assert handler.received["s1"] == [b"ok"] and handler.ended["s1"] == "Aborted"
        client.conn.send_headers(3, request("s3"))
        await client.data(3, message(b"y" * 1000) + message(b"z"), end=True)  # the limit itself passes
        assert await client.answered(3) == 0 and handler.received["s3"] == [b"y" * 1000, b"z"]


@pytest.mark.parametrize(
    "last, status",
    [
        pytest.param(message(b"packed", compressed=1), UNIMPLEMENTED, id="compressed"),
        *(
            pytest.param(message(bytes(2 * DIRECT_BYTES))[:cut], INTERNAL, id=f"ended-in-{where}")
            for cut, where in ((3, "prefix"), (50, "body"), (DIRECT_BYTES, "big-body"))
        ),
    ],
)
@asynchronous
async def test_a_message_that_cannot_be_read_fails_its_stream(last: bytes, status: int):
    handler = Handler()
    async with connected(handler) as (_, client):
        await client.data(1, message(b"whole") + last, end=True)
        assert await client.answered(1) == status and handler.received["s1"] == [b"whole"]


# --- streams and connections ending ---------------------------------------------------------------


@asynchronous
async def test_another_method_is_refused_while_the_open_write_stream_completes():
    encoder, handler = Encoder(), Handler()
    async with connected(handler, raw_first(encoder) + frame(DATA, 0, 1, message(b"0123456789")[:9])) as (_, client):
        other = encoder.encode(request("s3", b"/rerun.redap.v1alpha1.Catalog/FindEntries"))
        await client.send(frame(HEADERS, END_HEADERS | END_STREAM, 3, other))
        await client.until(lambda: client.of(RST_STREAM, 3))
        assert client.goaway() == (1, 0)  # NO_ERROR, stream 1 the last served
        assert client.of(RST_STREAM, 3) == [(0, 3, (7).to_bytes(4, "big"))]  # REFUSED_STREAM
        await client.send(frame(DATA, END_STREAM, 1, message(b"0123456789")[9:]))
        assert await client.answered(1) == 0 and handler.received["s1"] == [b"0123456789"]
        await client.until(lambda: client.closed)  # nothing more is served on it
        assert set(handler.metadata) == {"s1"}


@asynchronous
async def test_a_stream_reset_by_the_client_cancels_its_handler_and_is_not_answered():
    handler = Handler()
    async with connected(handler) as (_, client):
        await client.data(1, message(b"first") + message(b"half of it")[:8])
        await handler.wait(lambda: handler.received["s1"] == [b"first"])
        client.conn.reset_stream(1, error_code=8)  # CANCEL
        await client.send()
        await handler.wait(lambda: "s1" in handler.finished)
        assert handler.ended["s1"] == "CancelledError"
        client.conn.ping(b"roundtrp")  # what the server wrote about stream 1 comes before the ping's answer
        await client.send()
        await client.until(lambda: any(flags & ACK for flags, _, _ in client.of(PING)))
        assert 1 not in client.headers and client.of(DATA, 1) == []
        client.conn.send_headers(3, request("s3"))
        await client.data(3, message(b"next"), end=True)
        assert await client.answered(3) == 0 and handler.received["s3"] == [b"next"]


@asynchronous
async def test_a_client_gone_mid_stream_cancels_its_handler():
    handler = Handler()
    async with connected(handler) as (_, client):
        await client.data(1, message(b"first") + message(bytes(DIRECT_BYTES))[: DIRECT_BYTES // 2])
        await handler.wait(lambda: handler.received["s1"] == [b"first"])
        client.sock.close()
        await handler.wait(lambda: "s1" in handler.finished)
        assert handler.ended["s1"] == "CancelledError"


@asynchronous
async def test_stop_sends_goaway_and_cancels_running_handlers():
    handler = Handler()
    async with connected(handler) as (server, client):
        await client.data(1, message(b"first"))
        await handler.wait(lambda: handler.received["s1"] == [b"first"])
        await asyncio.wait_for(server.stop(), TIMEOUT)
        assert handler.ended["s1"] == "CancelledError" and "s1" in handler.finished
        await client.until(lambda: client.closed)
        assert client.goaway() == (1, 0) and client.status(1) is None


# --- protocol errors ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "bad, code",
    [
        pytest.param(frame(DATA, 0, 5, message(b"x")), 1, id="data-on-a-stream-never-opened"),
        pytest.param((MAX_FRAME + 1).to_bytes(3, "big") + bytes(2) + (1).to_bytes(4, "big"), 6, id="over-max-frame"),
        pytest.param(frame(HEADERS, END_HEADERS, 3, b"\xff\xff\xff\xff\xff"), 9, id="undecodable-hpack"),
        pytest.param(frame(HEADERS, END_HEADERS | PADDED, 3), 1, id="empty-padded"),
    ],
)
@asynchronous
async def test_a_protocol_error_ends_the_connection_with_goaway(bad: bytes, code: int):
    handler = Handler()
    async with connected(handler) as (_, client):
        await client.data(1, message(b"first"))
        await handler.wait(lambda: handler.received["s1"] == [b"first"])
        await client.send(bad)
        await client.until(lambda: client.goaway() is not None)
        assert client.goaway() == (1, code)
        await client.until(lambda: client.closed)
        await handler.wait(lambda: "s1" in handler.finished)
        assert handler.ended["s1"] != "returned" and client.status(1) is None


# --- what the handler answers ---------------------------------------------------------------------


def test_a_handler_failing_is_internal_without_its_details(caplog: pytest.LogCaptureFixture):
    async def fail(requests: AsyncIterator[bytes], call: Any, got: Got) -> None:
        got.append(await call.read())  # failing once the client sent everything: no reset races it
        raise RuntimeError("secret: /srv/depot/keys.json")

    @asynchronous
    async def scenario() -> None:
        async with connected(Handler(fail)) as (_, client):
            await client.data(1, message(b"x"), end=True)
            assert await client.answered(1) == INTERNAL
            assert client.details(1) and "secret" not in client.details(1) and "keys" not in client.details(1)

    with caplog.at_level(logging.ERROR):
        scenario()
    assert any(r.exc_info and "secret" in str(r.exc_info[1]) for r in caplog.records)  # the log has it


@asynchronous
async def test_abort_status_message_and_trailing_metadata_reach_the_client():
    async def answer(requests: AsyncIterator[bytes], call: Any, got: Got) -> Any:
        got.append(await call.read())
        call.set_trailing_metadata((("fleet-error-code", "QUOTA"),))
        if got[0] == b"abort":
            await call.abort(grpc.StatusCode.PERMISSION_DENIED, "détails 100%")
        assert await call.read() is grpc.aio.EOF
        return Reply()

    async with connected(Handler(answer)) as (_, client):
        await client.data(1, message(b"abort"))
        client.conn.send_headers(3, request("s3"))
        await client.data(3, message(b"fine"), end=True)
        assert await client.answered(1) == grpc.StatusCode.PERMISSION_DENIED.value[0]
        assert client.trailers(1)[b"grpc-message"] == b"d%C3%A9tails 100%25"  # percent-encoded UTF-8
        assert client.details(1) == "détails 100%" and client.trailers(1)[b"fleet-error-code"] == b"QUOTA"
        assert await client.answered(3) == 0 and client.answer(3) == message(REPLY)
        assert client.trailers(3)[b"fleet-error-code"] == b"QUOTA"


@asynchronous
async def test_binary_metadata_is_base64_both_ways_and_a_large_trailer_is_split_into_frames():
    report = "r" * 40_000  # over the 16 KiB frame every client accepts

    async def answer(requests: AsyncIterator[bytes], call: Any, got: Got) -> Any:
        got.append(await call.read())
        call.set_trailing_metadata((("x-echo-bin", call.invocation_metadata()[-1][1][::-1]), ("x-report", report)))
        return Reply()

    encoder = Encoder()
    block = encoder.encode([*request("s1"), (b"x-token-bin", base64.b64encode(b"\x00\xffkey").rstrip(b"="))])
    handler = Handler(answer)
    first = PREFACE + frame(SETTINGS, 0, 0) + frame(HEADERS, END_HEADERS, 1, block)
    async with connected(handler, first) as (_, client):
        await client.send(frame(DATA, END_STREAM, 1, message(b"x")))
        assert await client.answered(1) == 0
        assert handler.metadata["s1"]["x-token-bin"] == b"\x00\xffkey"  # decoded, as grpc.aio gives it
        trailers = client.trailers(1)
        assert base64.b64decode(trailers[b"x-echo-bin"] + b"==") == b"yek\xff\x00"
        assert trailers[b"x-report"] == report.encode()
        assert max(len(payload) for _, _, payload in client.of(CONTINUATION, 1) + client.of(HEADERS, 1)) <= 16384


@asynchronous
async def test_a_stream_answered_while_a_large_body_is_read_leaves_the_connection_serving():
    async def refuse_after_one(requests: AsyncIterator[bytes], call: Any, got: Got) -> Any:
        got.append(await call.read())  # runs once the server has taken all of the first send
        await call.abort(grpc.StatusCode.UNAUTHENTICATED, "no token")

    handler = Handler(refuse_after_one)
    async with connected(handler) as (_, client):
        data = message(b"small") + message(bytes(3 * DIRECT_BYTES))
        whole = frame(DATA, END_STREAM, 1, data)
        cut = 9 + 5 + 5 + DIRECT_BYTES // 2  # one DATA frame, sent up to the middle of the large body
        await client.send(whole[:cut])  # (raw: h2 sends nothing on a stream once it is answered)
        assert await client.answered(1) == grpc.StatusCode.UNAUTHENTICATED.value[0]
        await client.send(whole[cut:])  # the rest of the body, after the answer: dropped
        handler.serve = read_all
        client.conn.send_headers(3, request("s3"))
        await client.data(3, message(b"next"), end=True)
        assert await client.answered(3) == 0 and handler.received["s3"] == [b"next"]
        assert handler.received["s1"] == [b"small"]


# --- review findings ------------------------------------------------------------------------------


@asynchronous
async def test_binary_metadata_in_grpc_core_true_binary_form_is_given_as_sent():
    """grpc C-core sends a `-bin` value as a 0 byte then the raw bytes (no base64) to a peer whose
    SETTINGS carry GRPC_ALLOW_TRUE_BINARY_METADATA (0xfe03) = 1, as the gRPC server's opening
    SETTINGS (which the front relays to the client before the hand-over) do."""
    encoder = Encoder()
    block = encoder.encode([*request("s1"), (b"x-token-bin", b"\x00" + b"\x00\xffkey")])
    first, handler = PREFACE + frame(SETTINGS, 0, 0) + frame(HEADERS, END_HEADERS, 1, block), Handler()
    async with connected(handler, first) as (_, client):
        await client.send(frame(DATA, END_STREAM, 1, message(b"x")))
        assert await client.answered(1) == 0
        assert handler.metadata["s1"]["x-token-bin"] == b"\x00\xffkey"


@asynchronous
async def test_a_grpc_core_client_through_the_front_gets_its_binary_metadata_through(tmp_path: Path):
    """The same end to end: a grpcio client, the front, a gRPC server behind it."""
    upstream = grpc.aio.server()
    upstream_path = str(tmp_path / "grpc.sock")
    upstream.add_insecure_port(f"unix:{upstream_path}")
    await upstream.start()
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    handler = Handler()
    front = Front(listener, upstream_path, "v", WriteServer(handler, 1 << 20))
    front.start()
    try:
        async with grpc.aio.insecure_channel(f"127.0.0.1:{listener.getsockname()[1]}") as channel:
            write = channel.stream_unary(WRITE_PATH.decode())
            metadata = (("x-name", "s1"), ("x-token-bin", b"\x00\xffkey"))
            assert await write(iter([b"one"]), metadata=metadata, timeout=TIMEOUT) == REPLY
        assert handler.received["s1"] == [b"one"]
        assert handler.metadata["s1"]["x-token-bin"] == b"\x00\xffkey"
    finally:
        await front.stop()
        await upstream.stop(0)


@asynchronous
async def test_requests_can_be_relayed_with_grpc_aio_as_the_handler_relays_them(tmp_path: Path):
    """`routing.relay_source` passes each request the call reads to `Relay.send`, a grpc.aio call's
    `write`, which takes bytes only, while the front hands large requests over as memoryviews."""
    owned: list[bytes] = []

    async def owner_writes(requests: AsyncIterator[bytes], context: Any) -> bytes:
        async for r in requests:
            owned.append(r)
        return b""

    owner = grpc.aio.server()
    owner.add_generic_rpc_handlers(
        (
            grpc.method_handlers_generic_handler(
                "rerun.sdk_comms.v1alpha1.MessageProxyService",
                {"WriteMessages": grpc.stream_unary_rpc_method_handler(owner_writes)},
            ),
        )
    )
    owner_addr = f"unix:{tmp_path / 'owner.sock'}"
    owner.add_insecure_port(owner_addr)
    await owner.start()

    async def relay(requests: AsyncIterator[bytes], call: Any, got: Got) -> Any:
        async with grpc.aio.insecure_channel(owner_addr) as channel:
            method = channel.stream_unary(WRITE_METHOD, request_serializer=None, response_deserializer=None)
            to_owner = Relay(Owner("run", "node-b", owner_addr), method())
            while (request := await call.read()) is not grpc.aio.EOF:
                await to_owner.send(request)
                got.append(request)
            await to_owner.finish()
        return Reply()

    big = bytes(range(256)) * (DIRECT_BYTES // 256 + 1)
    try:
        async with connected(Handler(relay)) as (_, client):
            await client.data(1, message(b"small") + message(big), end=True)
            assert await client.answered(1) == 0
            assert owned == [b"small", big]
    finally:
        await owner.stop(0)


@asynchronous
async def test_a_header_table_size_from_the_client_is_acknowledged_in_the_next_header_block():
    settings = (1).to_bytes(2, "big") + (0).to_bytes(4, "big")  # HEADER_TABLE_SIZE 0
    first = PREFACE + frame(SETTINGS, 0, 0, settings) + frame(HEADERS, END_HEADERS, 1, Encoder().encode(request("s1")))
    async with connected(Handler(), first) as (_, client):
        await client.send(frame(DATA, END_STREAM, 1, message(b"x")))
        assert await client.answered(1) == 0
        assert client.of(HEADERS, 1)[0][2][0] == 0x20  # a dynamic table size update to 0 first


@asynchronous
async def test_a_header_list_within_the_announced_limit_is_served():
    """The server announces SETTINGS_MAX_HEADER_LIST_SIZE = MAX_HEADER_BLOCK (1 MiB), and its HPACK
    decoder keeps to it (not to hpack's default of 64 KiB)."""
    block = Encoder().encode([*request("s1"), (b"x-long", b"v" * 100_000)], huffman=False)
    first = PREFACE + frame(SETTINGS, 0, 0) + frame(HEADERS, END_HEADERS, 1, block)
    handler = Handler()
    async with connected(handler, first) as (_, client):
        await client.send(frame(DATA, END_STREAM, 1, message(b"x")))
        assert await client.answered(1) == 0 and handler.metadata["s1"]["x-long"] == "v" * 100_000
