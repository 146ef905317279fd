"""The depot's public gRPC port: a thin front before the gRPC server, which listens on a private
Unix socket in the data dir.

It exists for what gRPC's own transport cannot do on that port:

- answer plain HTTP/1.1 `GET /version`, which Rerun's 0.30-era clients ask before they speak gRPC;
- take HTTP/2 requests whose `:scheme` pseudo-header is neither `http` nor `https`. rerun-sdk 0.22
  sends its URL's scheme (`rerun+http`), which gRPC refuses before any handler runs, so the robot
  would only log "Error parsing ':scheme' metadata" instead of the depot's answer telling it which
  SDK to install. On such connections (and only those) the front re-encodes every request's
  headers with the scheme made `http`.

- serve WriteMessages itself (`h2_writes`): a connection whose first request is WriteMessages (the
  SDK's GrpcSink) is served in this process, at a fraction of what gRPC's Python server costs per
  message.

Every other connection is read up to the end of its first request's headers and then passed on
byte for byte both ways, with back-pressure: the front adds one local hop, not a protocol stack.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket

from hpack import Encoder, HeaderTuple

from services.api.h2 import (
    CONTINUATION,
    FRAME_HEAD,
    HEADERS,
    PREFACE,
    HeaderBlock,
    HeaderBlocks,
    ProtocolError,
    frame_head,
    header_frames,
)
from services.api.h2_writes import WRITE_PATH, WriteServer
from services.storage.splice import Ending, Splice

log = logging.getLogger("fleet.grpc")

_GOOD_SCHEMES = (b"http", b"https")
# What a connection may send before the front knows what it is, and how long it may take.
SNIFF_LIMIT = 1 << 20
HTTP1_LIMIT = 16384
SNIFF_TIMEOUT_S = 10.0
READ_BYTES = 65536


def _plain_scheme(value: bytes) -> bytes:
    return b"https" if value.endswith(b"https") else b"http"


class ClientStream:
    """The client-to-server half of one HTTP/2 connection, after the preface.

    Inspecting, it reads frames without changing anything until the first header block is complete.
    If that request's scheme is plain it says so (`feed` returns None and `passthrough` is set): the
    caller then forwards what it was given, and everything after, unchanged. Otherwise it rewrites
    from then on: every header block decoded (the client's compression table lives in `blocks`)
    and encoded again with the scheme fixed; all other frames unchanged."""

    def __init__(self) -> None:
        self.blocks = HeaderBlocks(SNIFF_LIMIT)
        self.encoder: Encoder | None = None  # set once rewriting
        self.passthrough = False
        self.first_path = b""  # the first request's :path, once known
        self._buf = bytearray()
        self._pos = 0

    @property
    def held(self) -> bytes:
        """What was fed while inspecting (all of it, unchanged), for the caller to send on."""
        return bytes(self._buf)

    def feed(self, data: bytes) -> bytes | None:
        """The bytes to send upstream for `data` (b"" while still inspecting), or None once the
        connection needs no rewriting: then the caller sends every byte it was given, as given."""
        self._buf += data
        out = bytearray()
        while len(self._buf) - self._pos >= FRAME_HEAD:
            length, kind, flags, stream = frame_head(self._buf, self._pos)
            end = self._pos + FRAME_HEAD + length
            if end > len(self._buf):
                break
            payload = bytes(self._buf[self._pos + FRAME_HEAD : end])
            start, self._pos = self._pos, end
            if kind in (HEADERS, CONTINUATION):
                block = self.blocks.add(kind, flags, stream, payload, start)
                if block is None:
                    continue
                if self.encoder is None:  # the first request: decide
                    self.first_path = next((v for k, v in block.headers if k == b":path"), b"")
                    if not self._needs_rewrite(block.headers):
                        self.passthrough = True
                        return None
                    self.encoder = Encoder()
                    out += self._buf[: block.start]
                out += self._encode(block)
            elif self.blocks.pending:
                raise ProtocolError("a header block was interrupted by another frame")
            elif self.encoder is not None:
                out += self._buf[start:end]
        if self.encoder is not None:  # rewriting: what was handled is no longer needed
            del self._buf[: self._pos]
            self._pos = 0
        elif len(self._buf) > SNIFF_LIMIT:
            raise ProtocolError("no request headers within the first MiB")
        return bytes(out)

    @staticmethod
    def _needs_rewrite(headers: list[HeaderTuple]) -> bool:
        return any(name == b":scheme" and value not in _GOOD_SCHEMES for name, value in headers)

    def _encode(self, block: HeaderBlock) -> bytes:
        assert self.encoder is not None
        fixed = [type(h)(h[0], _plain_scheme(h[1])) if h[0] == b":scheme" else h for h in block.headers]
        return header_frames(block.stream, self.encoder.encode(fixed, huffman=True), block.flags, block.priority)


def http1_answer(request: bytes, version: str) -> bytes:
    """The answer to a plain HTTP/1.x request on the gRPC port."""
    line = request.split(b"\r\n", 1)[0].decode("latin-1")
    method, _, rest = line.partition(" ")
    path = rest.partition(" ")[0].split("?", 1)[0]
    if path == "/version" and method in ("GET", "HEAD"):
        status, body = "200 OK", f"{version}\n"
    else:
        status = "404 Not Found"
        body = (
            "this is the depot's Rerun gRPC port: it answers gRPC and GET /version; "
            "the REST API is on the depot's HTTP port\n"
        )
    data = body.encode()
    head = (
        f"HTTP/1.1 {status}\r\ncontent-type: text/plain; charset=utf-8\r\ncontent-length: {len(data)}\r\n"
        "connection: close\r\n\r\n"
    ).encode()
    return head if method == "HEAD" else head + data


class _Connection:
    """One client connection on the public gRPC port, from the first byte to its close.

    `run` reads the start of the connection and decides; from then on the kernel moves the bytes
    (`services.storage.splice`), except from a client whose headers need rewriting, which `run` keeps reading. The
    sockets are closed by whoever finishes last, and never while `run` may still wait on them."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        client: socket.socket,
        upstream_path: str,
        version: str,
        writes: WriteServer | None,
    ) -> None:
        self._loop, self._upstream_path, self._version, self._writes = loop, upstream_path, version, writes
        self._client: socket.socket | None = client
        self._upstream: socket.socket | None = None
        self._splices: list[Splice] = []
        self._task: asyncio.Task[None] | None = None
        self._closed = False

    def start(self) -> asyncio.Task[None]:
        self._task = asyncio.create_task(self._run())
        return self._task

    async def _run(self) -> None:
        handed_over = False
        try:
            handed_over = await self._serve()
        except ProtocolError as exc:
            log.info("gRPC port: connection closed: %s", exc)
        except (TimeoutError, OSError) as exc:
            log.debug("gRPC port: connection closed: %s", exc or type(exc).__name__)
        except asyncio.CancelledError:
            pass  # closed from the other side, or the front is stopping
        finally:
            if not handed_over or self._ended():
                self._close()

    async def _recv(self) -> bytes:
        return await self._loop.sock_recv(self._require_client(), READ_BYTES)

    async def _serve(self) -> bool:
        """True once the rest of the connection is in other hands (the splices, or the writes)."""
        sniffed = b""
        async with asyncio.timeout(SNIFF_TIMEOUT_S):
            while len(sniffed) < len(PREFACE) and PREFACE.startswith(sniffed[: len(PREFACE)]):
                sniffed += await self._recv_some()
            if not sniffed.startswith(PREFACE):
                while b"\r\n\r\n" not in sniffed:
                    if len(sniffed) > HTTP1_LIMIT:
                        raise ProtocolError("neither HTTP/2 nor an HTTP/1 request")
                    sniffed += await self._recv_some()
                await self._loop.sock_sendall(self._require_client(), http1_answer(sniffed, self._version))
                return False
            # The gRPC server's own opening frames go to the client now: clients wait for the
            # server's SETTINGS before they send a request, and the request decides who serves.
            upstream = self._upstream = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            upstream.setblocking(False)
            await self._loop.sock_connect(upstream, self._upstream_path)
            await self._loop.sock_sendall(upstream, PREFACE)
            await self._loop.sock_sendall(self._require_client(), await self._server_preface(upstream))
            stream, data = ClientStream(), sniffed[len(PREFACE) :]
            while (out := stream.feed(data)) == b"":
                data = await self._recv_some()
        if out is None and self._writes is not None and stream.first_path == WRITE_PATH:
            # Served here: the gRPC server's connection is closed unused. The write server opens
            # with SETTINGS of its own, which replace the ones the client has (HTTP/2 allows both).
            upstream.close()
            self._upstream = None
            client, self._client = self._require_client(), None  # the write server's from now on
            await self._writes.take(client, stream.held)
            return True
        self._splice(upstream, self._require_client())
        if out is None:  # plain: what was held back, then the kernel moves the rest
            await self._loop.sock_sendall(upstream, stream.held)
            self._splice(self._require_client(), upstream)
            return True
        await self._loop.sock_sendall(upstream, out)
        while data := await self._recv():  # rewriting, for as long as the client sends
            out = stream.feed(data)
            if out:
                await self._loop.sock_sendall(upstream, out)
        upstream.shutdown(socket.SHUT_WR)
        return True  # the server's answers still flow until it closes

    async def _server_preface(self, upstream: socket.socket) -> bytes:
        """The gRPC server's first frames (its SETTINGS, perhaps a WINDOW_UPDATE), whole frames only."""
        data = b""
        while True:
            more = await self._loop.sock_recv(upstream, READ_BYTES)
            if not more:
                raise ProtocolError("the gRPC server closed the connection at its start")
            data += more
            pos = 0
            while len(data) - pos >= FRAME_HEAD:
                pos += FRAME_HEAD + frame_head(data, pos)[0]
            if pos == len(data) and data:
                return data

    def _require_client(self) -> socket.socket:
        assert self._client is not None
        return self._client

    async def _recv_some(self) -> bytes:
        data = await self._recv()
        if not data:
            raise ProtocolError("the client closed the connection before its first request")
        return data

    def _ended(self) -> bool:
        return all(splice.closed for splice in self._splices)

    def _splice(self, src: socket.socket, dst: socket.socket) -> None:
        """From now on the kernel moves what `src` sends to `dst`; at its end, `dst` is half-closed."""

        def done(ending: Ending) -> None:
            if ending is Ending.SOURCE_ENDED:
                with contextlib.suppress(OSError):
                    dst.shutdown(socket.SHUT_WR)
            self._one_way_done(ending is Ending.DESTINATION_FAILED)

        self._splices.append(Splice(self._loop, src.fileno(), dst.fileno(), done))

    def _one_way_done(self, failed: bool) -> None:
        """A spliced direction ended. Close when either side failed, when the server has closed a
        connection that `run` rewrites, or once both directions have ended."""
        if self._task is not None and not self._task.done():
            if failed or self._splices[0].closed:
                self._task.cancel()  # it closes the sockets once it no longer waits on them
            return
        if failed or self._ended():
            self._close()

    def _close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for splice in self._splices:
            splice.close()
        for sock in (self._client, self._upstream):
            if sock is not None:
                sock.close()


class Front:
    """Serves the public gRPC port on `sock` (a listening socket): accepts connections and serves
    each in its own task, passing HTTP/2 on to the gRPC server at the Unix socket `upstream_path`,
    except connections that start with WriteMessages, which `writes` serves (if given)."""

    def __init__(
        self, sock: socket.socket, upstream_path: str, version: str, writes: WriteServer | None = None
    ) -> None:
        self._sock, self._upstream_path, self._version, self._writes = sock, upstream_path, version, writes
        self._connections: set[asyncio.Task[None]] = set()
        self._accepting: asyncio.Task[None] | None = None

    def start(self) -> None:
        self._sock.setblocking(False)
        self._accepting = asyncio.create_task(self._accept())

    async def _accept(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            try:
                client, _ = await loop.sock_accept(self._sock)
            except OSError as exc:  # out of file descriptors, say: keep serving the others
                log.warning("gRPC port: accept failed (%s)", exc)
                await asyncio.sleep(0.1)
                continue
            client.setblocking(False)
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            task = _Connection(loop, client, self._upstream_path, self._version, self._writes).start()
            self._connections.add(task)
            task.add_done_callback(self._connections.discard)

    async def stop(self) -> None:
        """Stop accepting; connections end as the gRPC server behind them stops."""
        if self._accepting is not None:
            self._accepting.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._accepting
        self._sock.close()
        if self._writes is not None:
            await self._writes.stop()
