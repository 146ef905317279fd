"""One HTTP GET of a presigned URL, its body read on the event loop straight into a few buffers.

Why not botocore: a whole warm download read through botocore's stream takes a thread to block on
the store's socket, hands each piece to the event loop through two thread switches, and allocates
fresh memory for every piece (the kernel zeroes each new page as the socket's bytes land in it).
Sampled with perf during `benchmarks/serve.py --tier warm`, that was a third of the depot's CPU per
download beside the socket copies themselves. Here the event loop reads the store's socket as it
writes the client's (asyncio's `BufferedProtocol`: the kernel copies into the buffer handed out,
nothing in between), and stops reading while `depth` pieces wait to be sent. The buffers of pieces
sent are filled again, so a download holds at most `depth` + LENT_SPARE + 1 buffers of `piece` bytes
whatever the run's size, and none is zeroed more than once.

The store is asked with a URL signed for this one read (`S3Store.loop_read`): the request carries
no credential, and this module knows nothing of S3 but how an object GET answers. It assumes what
every S3-compatible store does on GET: HTTP/1.1 with a `Content-Length` (no chunked framing) and,
for a range, `206` with `Content-Range` (pinned by tests/services/storage/test_loop_get.py against
a scripted server and SeaweedFS).
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import ssl
from collections import deque
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import cast
from urllib.parse import urlsplit

from core.errors import ConflictError
from services.storage.objectstore import STREAM_DEPTH, STREAM_PIECE_BYTES, ObjectNotFoundError, StorageError
from services.storage.splice import Source

HEAD_LIMIT = 64 * 1024  # a store's answer head longer than this is refused
LENT_SPARE = 2  # buffers kept beyond `depth` and the one being filled: pieces the sender still writes
_ERROR_CODE = re.compile(rb"<Code>([A-Za-z0-9.]{1,64})</Code>")
_CONTENT_RANGE = re.compile(rb"bytes (\d+)-(\d+)/(\d+|\*)")


@dataclass(frozen=True)
class Reading:
    """How one GET reads: `depth` pieces of `piece` bytes at most waiting to be sent; `what` names
    the object in errors (never the signed URL, which opens it)."""

    what: str
    piece: int = STREAM_PIECE_BYTES
    depth: int = STREAM_DEPTH
    connect_timeout_s: float = 5.0
    read_timeout_s: float = 60.0
    tls: ssl.SSLContext | None = None


class _Answer(asyncio.BufferedProtocol):
    """The store's answer as it arrives: its head parsed, then its body cut into pieces."""

    def __init__(self, reading: Reading, start: int, length: int, hand_over: bool = False) -> None:
        self.reading = reading
        self.hand_over = hand_over  # stop reading once the head is in: the socket's rest is the caller's
        self.leading = b""  # with hand_over: the body's bytes that came with the head
        self.start, self.length = start, length
        self.transport: asyncio.Transport | None = None
        self.head = bytearray(HEAD_LIMIT)
        self.head_len = 0
        self.status = 0  # 0 while the head is read
        self.refused: _Refused | None = None  # an answer that is not the object: its error body
        self.piece = bytearray()
        self.piece_len = 0  # of `piece`, what this piece takes (the last one only what is left)
        self.filled = 0
        self.lent: deque[bytearray] = deque()  # buffers of pieces handed out, oldest first
        self.received = 0  # body bytes so far
        self.ready: deque[memoryview] = deque()
        self.failure: Exception | None = None
        self.paused = False
        self._waiter: asyncio.Future[None] | None = None

    # -- asyncio's side
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # a socket's transport (not checked with isinstance: another loop's, uvloop's, is no subclass)
        self.transport = cast(asyncio.Transport, transport)

    def get_buffer(self, sizehint: int) -> memoryview:
        if self.status == 0:
            return memoryview(self.head)[self.head_len :]
        if self.refused is not None:
            return self.refused.buffer()
        if self.filled == self.piece_len:  # a new piece: the last one only as long as what is left
            self.piece_len, self.filled = max(1, min(self.reading.piece, self.length - self.received)), 0
            self.piece = self._buffer(self.piece_len)
        return memoryview(self.piece)[self.filled : self.piece_len]

    def _buffer(self, size: int) -> bytearray:
        """A buffer for the next piece: one lent before that nothing holds a view of any more, else a
        new one. Reused because a new bytearray is zeroed first (7 % of the server's CPU in a whole
        warm download, perf), only to be written over by the socket's bytes."""
        for _ in range(len(self.lent)):
            buffer = self.lent.popleft()
            if len(buffer) >= size and _unviewed(buffer):
                return buffer
            self.lent.append(buffer)
        if len(self.lent) > self.reading.depth + LENT_SPARE:
            self.lent.popleft()  # viewed still, after all the others: held elsewhere for long, let it go
        return bytearray(size)

    def buffer_updated(self, nbytes: int) -> None:
        if self.status == 0:
            self._head_updated(nbytes)
        elif self.refused is not None:
            if self.refused.updated(nbytes):
                self._fail(self.refused.error())
        else:
            self._body_updated(nbytes)

    def eof_received(self) -> bool | None:
        return None  # close: the answer ends with the connection (Connection: close)

    def connection_lost(self, exc: Exception | None) -> None:
        if self.refused is not None:
            self._fail(self.refused.error())
        elif self.received < self.length:
            cause = f": {exc}" if exc is not None else ""
            self._fail(
                StorageError(
                    f"reading {self.reading.what} broke off after {self.start + self.received} of "
                    f"{self.start + self.length} bytes{cause}"
                )
            )
        self._wake()

    # -- the answer
    def _head_updated(self, nbytes: int) -> None:
        self.head_len += nbytes
        end = self.head.find(b"\r\n\r\n", 0, self.head_len)
        if end < 0:
            if self.head_len == len(self.head):
                self._fail(StorageError(f"reading {self.reading.what}: the store's answer head is over 64 KiB"))
            return
        rest = bytes(self.head[end + 4 : self.head_len])
        self._take_head(bytes(self.head[:end]))
        self.head = bytearray()
        if self.hand_over and self.failure is None and self.refused is None:
            self.leading = rest[: self.length]
            self.received = len(self.leading)
            if self.transport is not None:
                self.transport.pause_reading()
            self._wake()
            return
        while rest and self.failure is None:  # the body's first bytes came with the head
            view = self.get_buffer(len(rest))
            taken = min(len(view), len(rest))
            view[:taken] = rest[:taken]
            rest = rest[taken:]
            self.buffer_updated(taken)

    def _take_head(self, head: bytes) -> None:
        lines = head.split(b"\r\n")
        status = lines[0].split(b" ", 2)
        if len(status) < 2 or not status[0].startswith(b"HTTP/1.") or not status[1].isdigit():
            self.status = -1
            self._fail(StorageError(f"reading {self.reading.what}: the store's answer is not HTTP/1.1"))
            return
        self.status = int(status[1])
        fields = {
            name.strip().lower(): value.strip() for name, _, value in (line.partition(b":") for line in lines[1:])
        }
        size = int(fields[b"content-length"]) if fields.get(b"content-length", b"").isdigit() else None
        if self.status not in (200, 206):
            self.refused = _Refused(self.reading.what, self.status, size)
            if size == 0:
                self._fail(self.refused.error())
            return
        if size is None or b"chunked" in fields.get(b"transfer-encoding", b""):
            self._fail(StorageError(f"reading {self.reading.what}: the store sent no Content-Length"))
            return
        first = 0
        if self.status == 206:
            matched = _CONTENT_RANGE.fullmatch(fields.get(b"content-range", b""))
            first = int(matched.group(1)) if matched else -1
        if first != self.start or size != self.length:
            self._fail(
                StorageError(
                    f"reading {self.reading.what}: the store sent {size} bytes from {first}, not "
                    f"{self.length} from {self.start}: the object is not the one the catalog knows"
                )
            )

    def _body_updated(self, nbytes: int) -> None:
        self.filled += nbytes
        self.received += nbytes
        if self.received > self.length:
            self._fail(StorageError(f"reading {self.reading.what}: the store sent more than it announced"))
            return
        if self.filled == self.piece_len or self.received == self.length:
            self.ready.append(memoryview(self.piece)[: self.filled])
            self.lent.append(self.piece)
            self.piece, self.piece_len, self.filled = bytearray(), 0, 0
            if len(self.ready) >= self.reading.depth and self.transport is not None:
                self.transport.pause_reading()  # resumed as the sender takes pieces
                self.paused = True
            self._wake()

    def _fail(self, exc: Exception) -> None:
        if self.failure is None:
            self.failure = exc
        if self.transport is not None:
            self.transport.close()
        self._wake()

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)

    # -- the reader's side
    async def head_read(self) -> None:
        """Wait for the head of an answer read for hand-over; raises what the store answered instead."""
        while self.status == 0 or self.refused is not None:
            if self.failure is not None:
                raise self.failure
            await self._wait()
        if self.failure is not None:
            raise self.failure

    async def _wait(self) -> None:
        self._waiter = asyncio.get_running_loop().create_future()
        try:
            async with asyncio.timeout(self.reading.read_timeout_s):
                await self._waiter
        except TimeoutError:
            raise StorageError(
                f"reading {self.reading.what}: the store sent nothing for {self.reading.read_timeout_s:g} s"
            ) from None

    async def next_piece(self) -> memoryview | None:
        """The next piece of the body; None after the last."""
        while not self.ready:
            if self.failure is not None:
                raise self.failure
            if self.received == self.length:
                return None
            await self._wait()
        piece = self.ready.popleft()
        if self.paused and len(self.ready) < self.reading.depth and self.transport is not None:
            self.paused = False
            self.transport.resume_reading()
        return piece


def _unviewed(buffer: bytearray) -> bool:
    """Whether no view of `buffer` is alive any more (the sender's, a transport's that keeps what it
    could not send yet): a bytearray cannot be resized while one is. Shrunk by one byte and grown
    back, which moves nothing (bytearray keeps its allocation for a small shrink)."""
    try:
        del buffer[-1]
    except BufferError:
        return False
    buffer.append(0)
    return True


ERROR_BODY_LIMIT = 4096  # of an error's body, read for the S3 error code it names


class _Refused:
    """An answer that is not the object: its error body (XML naming an S3 error code), read up to
    ERROR_BODY_LIMIT bytes, then the error it stands for."""

    def __init__(self, what: str, status: int, size: int | None) -> None:
        self.what, self.status = what, status
        self.size = min(size, ERROR_BODY_LIMIT) if size is not None else ERROR_BODY_LIMIT
        self.body = bytearray(self.size)
        self.filled = 0

    def buffer(self) -> memoryview:
        return memoryview(self.body)[self.filled :] if self.filled < self.size else memoryview(bytearray(4096))

    def updated(self, nbytes: int) -> bool:
        """Take `nbytes` more; True once the body (or as much as is kept) is here."""
        self.filled = min(self.size, self.filled + nbytes)
        return self.filled >= self.size

    def error(self) -> Exception:
        matched = _ERROR_CODE.search(self.body, 0, self.filled)
        code = matched.group(1).decode("ascii") if matched else ""
        if self.status == 404 or code in ("NoSuchKey", "NoSuchBucket"):
            return ObjectNotFoundError(f"no object {self.what}")
        if code == "InvalidObjectState":
            return ConflictError(f"{self.what} is archived: restore it before reading")
        return StorageError(f"reading {self.what}: the store answered HTTP {self.status} {code}".rstrip())


async def get(url: str, start: int, length: int, reading: Reading) -> AsyncIterator[memoryview]:
    """The object at `url` from `start` to its end (`length` bytes: what the caller knows of it; an
    object of another size is refused), in pieces as they arrive. Raises
    ObjectNotFoundError for a missing object, ConflictError for an archived one, StorageError for
    any other failure (naming `reading.what`, never the URL)."""
    if length <= 0:
        return
    answer = _Answer(reading, start, length)
    transport = await _ask(url, start, answer, reading)
    try:
        while (piece := await answer.next_piece()) is not None:
            yield piece
    finally:
        transport.close()


def spliceable(url: str) -> bool:
    """Whether a GET of `url` can be handed over (`opened`): plain HTTP, whose bytes need no decrypting."""
    return urlsplit(url).scheme == "http"


@contextlib.asynccontextmanager
async def opened(url: str, start: int, length: int, reading: Reading) -> AsyncIterator[Source]:
    """As `get`, answered and its head checked, but the body is the caller's to read from the socket
    while the context is open (a plain-HTTP `url`: `spliceable`). The same errors as `get`."""
    if not spliceable(url):
        raise StorageError(f"reading {reading.what}: only a plain-HTTP answer can be handed over")
    answer = _Answer(reading, start, length, hand_over=True)
    transport = await _ask(url, start, answer, reading)
    try:
        await answer.head_read()
        sock = transport.get_extra_info("socket")
        yield Source(answer.leading, sock.fileno(), length - len(answer.leading), reading.read_timeout_s)
    finally:
        transport.close()


async def _ask(url: str, start: int, answer: _Answer, reading: Reading) -> asyncio.Transport:
    """A connection to the store with the GET of `url` from `start` sent, `answer` reading it."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or parts.hostname is None:
        raise StorageError(f"reading {reading.what}: not an http(s) URL")
    tls = (reading.tls or ssl.create_default_context()) if parts.scheme == "https" else None
    loop = asyncio.get_running_loop()
    try:
        async with asyncio.timeout(reading.connect_timeout_s):
            transport, _ = await loop.create_connection(
                lambda: answer, parts.hostname, parts.port or (443 if tls else 80), ssl=tls
            )
    except (OSError, TimeoutError) as exc:
        raise StorageError(f"reading {reading.what}: cannot reach the store: {exc or 'timed out'}") from None
    target = parts.path + (f"?{parts.query}" if parts.query else "")
    ranged = f"Range: bytes={start}-\r\n" if start else ""  # from 0: the object as it is sent whole
    transport.write(
        f"GET {target} HTTP/1.1\r\nHost: {parts.netloc}\r\n{ranged}Connection: close\r\n\r\n".encode("ascii")
    )
    return transport
