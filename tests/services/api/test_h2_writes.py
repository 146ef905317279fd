"""WriteMessages served by the front (`h2_writes`), driven over a loopback socket without a server:
an HTTP/2 client (h2, or raw frames for what h2 will not send) on one end, `WriteServer.take` on
the other, and a handler that records what each stream brought and how it ended."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import functools
import itertools
import logging
import socket
import time
import tracemalloc
import urllib.parse
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine
from pathlib import Path
from typing import Any

import grpc
import h2.config
import h2.connection
import pytest
from hpack import Decoder, Encoder

from services.api.grpc_front import Front
from services.api.h2_writes import DIRECT_BYTES, MAX_FRAME, WRITE_PATH, WriteServer
from services.cluster.ownership import Owner
from services.cluster.relay import WRITE_METHOD, Relay

PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"
DATA, HEADERS, RST_STREAM, SETTINGS, PING, GOAWAY, WINDOW_UPDATE, CONTINUATION = 0x0, 0x1, 0x3, 0x4, 0x6, 0x7, 0x8, 0x9
END_STREAM, ACK, END_HEADERS, PADDED, PRIORITY = 0x1, 0x1, 0x4, 0x8, 0x20
TIMEOUT = 5.0  # any one wait; a test that hangs fails in this
REPLY = b"\x08\x2a"  # what the handler answers, serialized
INTERNAL, UNIMPLEMENTED = grpc.StatusCode.INTERNAL.value[0], grpc.StatusCode.UNIMPLEMENTED.value[0]


def frame(kind: int, flags: int, stream: int, payload: bytes = b"") -> bytes:
    return len(payload).to_bytes(3, "big") + bytes((kind, flags)) + stream.to_bytes(4, "big") + payload


def message(body: bytes, compressed: int = 0) -> bytes:
    return bytes((compressed,)) + len(body).to_bytes(4, "big") + body


def request(name: str, path: bytes = WRITE_PATH) -> list[tuple[bytes, bytes]]:
    head = b":method POST|:scheme http|:authority depot:51234|content-type application/grpc|te trailers"
    fields = [(k, v) for k, _, v in (f.partition(b" ") for f in head.split(b"|"))]
    return [(b":path", path), *fields, (b"x-name", name.encode())]


def raw_first(encoder: Encoder, name: str = "s1") -> bytes:
    """What a client sends first, as raw frames: preface, settings, its WriteMessages request."""
    return PREFACE + frame(SETTINGS, 0, 0) + frame(HEADERS, END_HEADERS, 1, encoder.encode(request(name)))


def asynchronous(test: Callable[..., Coroutine[Any, Any, None]]) -> Callable[..., None]:
    """An async test run under `asyncio.run`, bounded as a whole."""

    @functools.wraps(test)
    def run(*args: Any, **kwargs: Any) -> None:
        asyncio.run(asyncio.wait_for(test(*args, **kwargs), 15))

    return run


class Client:
    """The client's end: sends through its h2 connection (if any) or raw, and parses every frame the
    server sends (header blocks decoded), feeding them to h2 too (which checks them)."""

    def __init__(self, sock: socket.socket, conn: h2.connection.H2Connection | None) -> None:
        self.sock, self.h2 = sock, conn
        self.frames: list[tuple[int, int, int, bytes]] = []  # kind, flags, stream, payload
        self.headers: dict[int, list[dict[bytes, bytes]]] = {}
        self.closed = False
        self._pending, self._block, self._decoder = b"", b"", Decoder()

    @property
    def conn(self) -> h2.connection.H2Connection:
        assert self.h2 is not None
        return self.h2

    async def send(self, raw: bytes = b"") -> None:
        data = (self.h2.data_to_send() if self.h2 is not None else b"") + raw
        await asyncio.wait_for(asyncio.get_running_loop().sock_sendall(self.sock, data), TIMEOUT)

    async def data(self, stream: int, payload: bytes, end: bool = False, pad: int | None = None) -> None:
        self.conn.send_data(stream, payload, end_stream=end, pad_length=pad)
        await self.send()

    async def until(self, done: Callable[[], object], timeout: float = TIMEOUT) -> None:
        async def read() -> None:
            while not done():
                assert not self.closed, "the server closed the connection"
                await self._read()

        await asyncio.wait_for(read(), timeout)

    async def answered(self, stream: int, timeout: float = TIMEOUT) -> int:
        """The stream's grpc-status, once it came."""
        await self.until(lambda: self.status(stream) is not None, timeout)
        return self.status(stream) or 0

    async def _read(self) -> None:
        try:
            data = await asyncio.get_running_loop().sock_recv(self.sock, 1 << 20)
        except ConnectionResetError:
            data = b""
        if not data:
            self.closed = True
            return
        buf, pos = self._pending + data, 0
        while len(buf) - pos >= 9 and len(buf) - pos >= 9 + (length := int.from_bytes(buf[pos : pos + 3], "big")):
            kind, flags, stream = buf[pos + 3], buf[pos + 4], int.from_bytes(buf[pos + 5 : pos + 9], "big")
            payload = buf[pos + 9 : pos + 9 + length]
            pos += 9 + length
            self.frames.append((kind, flags, stream, payload))
            if kind in (HEADERS, CONTINUATION):
                self._block += payload
                if flags & END_HEADERS:
                    self.headers.setdefault(stream, []).append(dict(self._decoder.decode(self._block, raw=True)))
                    self._block = b""
        self._pending = buf[pos:]
        if self.h2 is not None:
            self.h2.receive_data(data)
            await self.send()  # its acknowledgements

    def of(self, kind: int, stream: int | None = None) -> list[tuple[int, int, bytes]]:
        return [(f, s, p) for k, f, s, p in self.frames if k == kind and stream in (None, s)]

    def trailers(self, stream: int) -> dict[bytes, bytes]:
        blocks = [block for block in self.headers.get(stream, []) if b"grpc-status" in block]
        return blocks[-1] if blocks else {}

    def status(self, stream: int) -> int | None:
        status = self.trailers(stream).get(b"grpc-status")
        return None if status is None else int(status)

    def details(self, stream: int) -> str:
        return urllib.parse.unquote(self.trailers(stream).get(b"grpc-message", b"").decode("ascii"), errors="strict")

    def answer(self, stream: int) -> bytes:
        return b"".join(payload for _, _, payload in self.of(DATA, stream))

    def goaway(self) -> tuple[int, int] | None:
        frames = self.of(GOAWAY)
        return (int.from_bytes(frames[0][2][:4], "big"), int.from_bytes(frames[0][2][4:8], "big")) if frames else None


class Reply:
    def SerializeToString(self) -> bytes:
        return REPLY


class Got(list[bytes]):
    """What a stream's handler received; each request wakes the handler's waiters."""

    def __init__(self, changed: asyncio.Event) -> None:
        super().__init__()
        self._changed = changed

    def append(self, request: Any) -> None:
        super().append(bytes(request))
        self._changed.set()


Serve = Callable[[AsyncIterator[bytes], Any, Got], Awaitable[Any]]


async def read_all(requests: AsyncIterator[bytes], call: Any, got: Got) -> Any:
    async for request in requests:
        got.append(request)
    return Reply()


class Handler:
    """The WriteMessages handler: per stream (named by its x-name metadata) what it received, its
    metadata, how it ended ("returned" or the exception's name) and whether its `finally` ran."""

    def __init__(self, serve: Serve = read_all) -> None:
        self.serve = serve
        self.received: dict[str, Got] = {}
        self.metadata: dict[str, dict[str, Any]] = {}
        self.ended: dict[str, str] = {}
        self.finished: set[str] = set()
        self.changed = asyncio.Event()

    async def __call__(self, requests: AsyncIterator[bytes], call: Any) -> Any:
        metadata = dict(call.invocation_metadata())
        name = metadata["x-name"]
        self.metadata[name], got = metadata, self.received.setdefault(name, Got(self.changed))
        try:
            result = await self.serve(requests, call, got)
            self.ended[name] = "returned"
            return result
        except BaseException as exc:
            self.ended[name] = type(exc).__name__
            raise
        finally:
            self.finished.add(name)
            self.changed.set()

    async def wait(self, done: Callable[[], object]) -> None:
        async def watch() -> None:
            while not done():
                self.changed.clear()
                await self.changed.wait()

        await asyncio.wait_for(watch(), TIMEOUT)


def tcp_pair(buffer: int = 0, back_buffer: int = 0) -> tuple[socket.socket, socket.socket]:
    """A connected loopback pair (client, server); `buffer`: small kernel buffers client to server,
    `back_buffer`: server to client."""
    listener, client = socket.socket(), socket.socket()
    for sock, option in ((listener, socket.SO_RCVBUF), (client, socket.SO_SNDBUF)) if buffer else ():
        sock.setsockopt(socket.SOL_SOCKET, option, buffer)
    for sock, option in ((listener, socket.SO_SNDBUF), (client, socket.SO_RCVBUF)) if back_buffer else ():
        sock.setsockopt(socket.SOL_SOCKET, option, back_buffer)
    with listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        client.connect(listener.getsockname())
        server, _ = listener.accept()
    client.setblocking(False)
    return client, server


@contextlib.asynccontextmanager
async def connected(
    handler: Handler,
    first: bytes | None = None,
    *,
    max_message: int = 4 << 20,
    via_socket: bool = False,
    buffer: int = 0,
    back_buffer: int = 0,
) -> AsyncIterator[tuple[WriteServer, Client]]:
    """A write connection as the front hands it over, its client having sent `first` (the preface and
    its first request; None: an h2 client opening stream 1, named s1): what followed the preface is
    `held`, or (`via_socket`) the preface is read off the socket here and the server reads the rest."""
    conn = None
    if first is None:
        conn = h2.connection.H2Connection(h2.config.H2Configuration(client_side=True, header_encoding=None))
        conn.initiate_connection()
        conn.send_headers(1, request("s1"))
        first = conn.data_to_send()
    assert first.startswith(PREFACE)
    client_sock, server_sock = tcp_pair(buffer, back_buffer)
    server, client = WriteServer(handler, max_message), Client(client_sock, conn)
    try:
        if via_socket:
            await client.send(first)
            server_sock.settimeout(TIMEOUT)
            assert server_sock.recv(len(PREFACE), socket.MSG_WAITALL) == PREFACE
        await server.take(server_sock, b"" if via_socket else first[len(PREFACE) :])
        await client.until(lambda: client.of(SETTINGS) and client.of(WINDOW_UPDATE))
        yield server, client
    finally:
        client_sock.close()
        await asyncio.wait_for(server.stop(), TIMEOUT)
        server_sock.close()


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


@asynchronous
async def test_keepalive_pings_a_silent_client_and_closes_one_that_does_not_answer(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr("services.api.h2_writes.KEEPALIVE_S", 0.15)
    monkeypatch.setattr("services.api.h2_writes.KEEPALIVE_TIMEOUT_S", 0.3)
    handler, started = Handler(), time.monotonic()
    async with connected(handler, raw_first(Encoder())) as (_, client):

        def pings() -> list[bytes]:
            return [payload for flags, _, payload in client.of(PING) if not flags & ACK]

        await client.until(pings)
        assert time.monotonic() - started >= 0.15 - 0.02 and len(pings()[0]) == 8
        await client.send(frame(PING, ACK, 0, pings()[0]))  # answered: pinged again later, not closed
        await client.until(lambda: len(pings()) == 2)
        second_ping = time.monotonic()
        await client.until(lambda: client.closed)  # not answered: closed, not before the timeout
        assert time.monotonic() - second_ping >= 0.3 - 0.05
        await handler.wait(lambda: "s1" in handler.finished)
        assert handler.ended["s1"] == "CancelledError"


# --- back-pressure --------------------------------------------------------------------------------


async def send_until_stalled(sock: socket.socket, data: bytes, stall: float) -> int:
    """Send until the socket takes nothing for `stall` seconds: how much was sent."""
    loop, sent = asyncio.get_running_loop(), 0
    while sent < len(data):
        try:
            sent += sock.send(data[sent : sent + 65536])
        except BlockingIOError:
            writable: asyncio.Future[None] = loop.create_future()
            loop.add_writer(sock, functools.partial(writable.set_result, None))
            try:
                await asyncio.wait_for(writable, stall)
            except TimeoutError:
                return sent
            finally:
                loop.remove_writer(sock)
    return sent


@asynchronous
async def test_a_handler_that_does_not_read_stops_the_connection_reading(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr("services.api.h2_writes.QUEUE_LIMIT", 256 << 10)
    bodies = [bytes([i % 256]) * (100_000, 1_000, 30_000)[i % 3] for i in range(180)]  # 7.9 MB
    stream = b"".join(message(body) for body in bodies)
    data = b"".join(frame(DATA, 0, 1, stream[i : i + 250_000]) for i in range(0, len(stream), 250_000))
    go = asyncio.Event()

    async def read_when_told(requests: AsyncIterator[bytes], call: Any, got: Got) -> bytes:
        await go.wait()
        while (request := await call.read()) is not grpc.aio.EOF:
            got.append(request)
        return b"read"

    handler = Handler(read_when_told)
    async with connected(handler, raw_first(Encoder()), buffer=64 << 10) as (_, client):
        sent = await send_until_stalled(client.sock, data, stall=0.3)
        # what the server read: its queue limit, a read buffer and the kernel's buffers, no more
        assert sent < 2_500_000 and handler.received["s1"] == []
        go.set()
        await client.send(data[sent:] + frame(DATA, END_STREAM, 1))
        assert await client.answered(1) == 0 and client.answer(1) == message(b"read")
        assert handler.received["s1"] == bodies


@asynchronous
async def test_what_a_refused_stream_held_unread_is_released(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr("services.api.h2_writes.QUEUE_LIMIT", 64 << 10)
    encoder = Encoder()  # stream 1's 100 kB are all queued when the hand-over feeds them, before it is refused
    first = raw_first(encoder) + frame(DATA, 0, 1, b"".join(message(bytes(20_000)) for _ in range(5)))

    async def refuse(requests: AsyncIterator[bytes], call: Any, got: Got) -> None:
        await call.abort(grpc.StatusCode.UNAUTHENTICATED, "no token")

    handler = Handler(refuse)
    async with connected(handler, first) as (_, client):
        assert await client.answered(1) == grpc.StatusCode.UNAUTHENTICATED.value[0]
        handler.serve = read_all
        request3 = encoder.encode(request("s3"))
        await client.send(frame(HEADERS, END_HEADERS, 3, request3) + frame(DATA, END_STREAM, 3, message(b"again")))
        assert await client.answered(3, timeout=2) == 0 and handler.received["s3"] == [b"again"]


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


async def roundtrip(client: Client, payload: bytes = b"roundtrp") -> None:
    """A PING answered: the server has parsed everything sent before it."""
    await client.send(frame(PING, 0, 0, payload))
    await client.until(lambda: any(flags & ACK and p == payload for flags, _, p in client.of(PING)))


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
async def test_a_declared_message_length_is_not_allocated_before_its_bytes_come():
    """A message's 5-byte prefix names its length. Were its buffer allocated whole from that, a few
    hundred bytes from a client (100 streams, each declaring FLEET_MAX_MESSAGE_SIZE) would make the
    server allocate gigabytes: what is allocated ahead of the bytes is bounded per connection."""
    declared, streams = 16 << 20, 8
    tracemalloc.start()
    try:
        async with connected(Handler(), max_message=declared) as (_, client):
            before = tracemalloc.get_traced_memory()[0]
            for i in range(streams):
                stream = 1 + 2 * i
                if stream != 1:
                    client.conn.send_headers(stream, request(f"s{stream}"))
                await client.data(stream, (0).to_bytes(1, "big") + declared.to_bytes(4, "big") + b"xyz")
            await roundtrip(client)
            grown = tracemalloc.get_traced_memory()[0] - before
            assert grown < 32 << 20, f"{grown >> 20} MiB held for {streams * 8} bytes of message"
    finally:
        tracemalloc.stop()


async def send_until_stalled_or_closed(sock: socket.socket, data: bytes, stall: float) -> int:
    with contextlib.suppress(ConnectionError):
        return await send_until_stalled(sock, data, stall)
    return -1


@asynchronous
async def test_pings_from_a_client_that_reads_nothing_do_not_pile_up_in_the_server():
    """Every PING (and SETTINGS, and refused HEADERS) is answered with a write; from a client that
    sends them and reads nothing, the server stops reading once its answers fill the transport's
    write buffer, instead of buffering them without limit."""
    handler = Handler()
    pings = b"".join(frame(PING, 0, 0, i.to_bytes(8, "big")) for i in range(150_000))  # 2.5 MB
    async with connected(handler, raw_first(Encoder()), buffer=32 << 10, back_buffer=32 << 10) as (_, client):
        sent = await send_until_stalled_or_closed(client.sock, pings, stall=0.5)
        assert sent < len(pings)


@asynchronous
async def test_stop_ends_a_connection_whose_client_reads_nothing():
    """`WriteServer.stop` cancels the handlers at once and aborts a transport whose client reads
    nothing (closing it would wait for its unsent bytes for ever)."""
    handler = Handler()
    pings = b"".join(frame(PING, 0, 0, i.to_bytes(8, "big")) for i in range(30_000))  # 510 kB
    async with connected(handler, raw_first(Encoder()), buffer=32 << 10, back_buffer=32 << 10) as (server, client):
        await send_until_stalled_or_closed(client.sock, pings, stall=0.5)
        await asyncio.wait_for(server.stop(), 2)
        assert handler.ended["s1"] == "CancelledError"


@asynchronous
async def test_keepalive_does_not_close_a_connection_that_back_pressure_paused(monkeypatch: pytest.MonkeyPatch):
    """While reading is paused (a handler slow to take what came), nothing is read, the client's
    answers to pings included: the keepalive does not take that silence for a dead client."""
    monkeypatch.setattr("services.api.h2_writes.QUEUE_LIMIT", 64 << 10)
    monkeypatch.setattr("services.api.h2_writes.KEEPALIVE_S", 0.4)
    monkeypatch.setattr("services.api.h2_writes.KEEPALIVE_TIMEOUT_S", 0.6)
    bodies = [bytes([i]) * 20_000 for i in range(100)]  # 2 MB
    stream = b"".join(message(body) for body in bodies)
    data = b"".join(frame(DATA, 0, 1, stream[i : i + 250_000]) for i in range(0, len(stream), 250_000))
    go = asyncio.Event()

    async def read_when_told(requests: AsyncIterator[bytes], call: Any, got: Got) -> Any:
        await go.wait()
        while (request := await call.read()) is not grpc.aio.EOF:
            got.append(request)
        return Reply()

    handler = Handler(read_when_told)
    async with connected(handler, raw_first(Encoder()), buffer=64 << 10) as (_, client):
        sent = await send_until_stalled(client.sock, data, stall=0.2)
        assert sent < len(data)  # paused

        def pings() -> list[bytes]:
            return [payload for flags, _, payload in client.of(PING) if not flags & ACK]

        await client.until(pings)  # the server pings the client it does not read (no answer can
        # come while the client is in the middle of a frame; none could be read anyway),
        with pytest.raises(TimeoutError):  # and does not close it for that (twice the timeout's time)
            await client.until(lambda: False, timeout=1.2)
        go.set()
        await client.send(data[sent:] + frame(DATA, END_STREAM, 1))
        assert await client.answered(1) == 0 and handler.received["s1"] == bodies


@asynchronous
async def test_a_stream_whose_handler_does_not_read_leaves_the_other_streams_flowing():
    """Flow control is per stream in HTTP/2 and gRPC: a stream whose handler does not read stops
    within its window, and the connection's other streams go on (a stream's window comes back as its
    handler takes what it was sent, not as it is parsed)."""
    go = asyncio.Event()

    async def first_slow(requests: AsyncIterator[bytes], call: Any, got: Got) -> Any:
        if dict(call.invocation_metadata())["x-name"] == "s1":
            await go.wait()
        return await read_all(requests, call, got)

    handler = Handler(first_slow)
    stream = b"".join(message(bytes([i % 256]) * 60_000) for i in range(700))  # 42 MB
    async with connected(handler) as (_, client):
        loop, sent = asyncio.get_running_loop(), 0
        deadline = loop.time() + 2.0
        while sent < len(stream) and loop.time() < deadline:  # within the windows the server gives
            room = min(client.conn.local_flow_control_window(1), 1 << 20, len(stream) - sent)
            if room:
                await client.data(1, stream[sent : sent + room])
                sent += room
            else:
                with contextlib.suppress(TimeoutError):
                    await client.until(lambda: client.conn.local_flow_control_window(1) > 0, timeout=0.2)
        assert sent < len(stream)  # stream 1 stopped, as it should
        client.conn.send_headers(3, request("s3"))
        await client.data(3, message(b"other stream"), end=True)
        try:
            assert await client.answered(3, timeout=2) == 0 and handler.received["s3"] == [b"other stream"]
        finally:
            go.set()


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
