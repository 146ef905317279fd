"""What the write transport's tests (`h2_writes`) drive it with, over a loopback socket and without
a server: an HTTP/2 client (h2, or raw frames for what h2 will not send) on one end,
`WriteServer.take` on the other, and a handler that records what each stream brought and how it
ended."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import socket
import urllib.parse
from collections.abc import AsyncIterator, Awaitable, Callable, Coroutine
from typing import Any

import grpc
import h2.config
import h2.connection
from hpack import Decoder, Encoder

from services.api.h2_writes import WRITE_PATH, WriteServer

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


async def roundtrip(client: Client, payload: bytes = b"roundtrp") -> None:
    """A PING answered: the server has parsed everything sent before it."""
    await client.send(frame(PING, 0, 0, payload))
    await client.until(lambda: any(flags & ACK and p == payload for flags, _, p in client.of(PING)))


async def send_until_stalled_or_closed(sock: socket.socket, data: bytes, stall: float) -> int:
    with contextlib.suppress(ConnectionError):
        return await send_until_stalled(sock, data, stall)
    return -1
