"""One WriteMessages stream served by the front (`h2_writes`), as its handler sees it.

The handler is the one gRPC calls (`MessageProxy.write_messages`); a `WriteCall` has the few methods
of `grpc.aio.ServicerContext` it uses, and gives it the stream's requests in the order they came.
"""

from __future__ import annotations

import asyncio
import collections
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, NoReturn, Protocol, TypeAlias

import grpc
import numpy as np
import numpy.typing as npt

Body: TypeAlias = npt.NDArray[np.uint8]


def new_body(size: int) -> Body:
    """A message body's buffer, not zero-filled (its bytes are all written before it is read):
    a multi-MB message is then written once, by the socket, not also by a memset."""
    return np.empty(size, dtype=np.uint8)


class Aborted(Exception):
    """A stream ends with this gRPC status (the handler's `abort`, or what the transport found)."""

    def __init__(self, code: grpc.StatusCode, details: str) -> None:
        super().__init__(details)
        self.code, self.details = code, details


def grpc_message(details: str) -> str:
    """A status message as gRPC carries it in a trailer: percent-encoded UTF-8."""
    return "".join(
        chr(b) if 0x20 <= b <= 0x7E and b != 0x25 else f"%{b:02X}" for b in details.encode("utf-8", "replace")
    )


class Accounting(Protocol):
    """The connection's side of what its streams' handlers were given and took (back-pressure)."""

    def delivered(self, stream: int, nbytes: int) -> None: ...

    def taken(self, stream: int, nbytes: int) -> None: ...


class BodyBudget:
    """What the bodies being received on one connection have allocated ahead of their bytes: at
    most `limit` in all (at least `minimum` a body), beyond which a body grows as its bytes come; and
    the largest message taken."""

    def __init__(self, limit: int, minimum: int, max_message: int) -> None:
        self.limit, self.minimum, self.max_message = limit, minimum, max_message
        self.used = 0

    def ahead(self, length: int) -> int:
        return min(length, max(self.minimum, self.limit - self.used))


class WriteCall:
    """The requests of one stream, fed by its connection, and what the handler says of its answer."""

    def __init__(
        self, stream_id: int, metadata: tuple[tuple[str, Any], ...], accounting: Accounting, budget: BodyBudget
    ) -> None:
        self.stream_id, self._metadata = stream_id, metadata
        self._accounting, self._budget = accounting, budget
        self._queue: collections.deque[bytes | memoryview] = collections.deque()
        self._waiter: asyncio.Future[None] | None = None
        self._failure: Aborted | None = None
        self.ended = False  # the client sent the end of its requests
        self.dropping = False  # what more the client sends is dropped (the stream failed or was answered)
        self.trailing: tuple[tuple[str, str | bytes], ...] = ()  # a `-bin` key's value may be bytes
        # the message being put together: its 5-byte prefix (while split over frames), then its body
        self.header = bytearray()
        self.body: Body | None = None
        self.length = 0  # the body's, as its prefix declares
        self.filled = 0

    # --- what the handler calls (grpc.aio.ServicerContext's names) --------------------------

    def invocation_metadata(self) -> tuple[tuple[str, Any], ...]:
        return self._metadata

    def peer(self) -> str:
        return "front"  # a client of the public port (never another node: they use the peer port)

    def set_trailing_metadata(self, metadata: tuple[tuple[str, str | bytes], ...]) -> None:
        self.trailing = metadata

    async def abort(self, code: grpc.StatusCode, details: str = "") -> NoReturn:
        raise Aborted(code, details)

    async def read(self) -> Any:
        """The next request's bytes, or `grpc.aio.EOF` after the last."""
        while not self._queue:
            if self._failure is not None:
                raise self._failure
            if self.ended:
                return grpc.aio.EOF
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        request = self._queue.popleft()
        self._accounting.taken(self.stream_id, len(request))
        return request

    async def requests(self) -> AsyncIterator[bytes]:
        while (request := await self.read()) is not grpc.aio.EOF:
            yield request

    # --- what the connection calls ----------------------------------------------------------

    def deliver(self, request: bytes | memoryview) -> None:
        self._queue.append(request)
        self._accounting.delivered(self.stream_id, len(request))
        self._wake()

    def cut(self, data: memoryview) -> None:
        """Cut gRPC messages (a flag byte, a 4-byte length, the message) out of the stream's data:
        small ones whole as bytes, larger ones put together in a buffer of their own (which the
        connection may also read the socket straight into: `room`, `complete`)."""
        pos, size = 0, len(data)
        while pos < size and not self.dropping:
            if self.body is not None:  # inside a message
                take = min(size - pos, self.length - self.filled)
                self.room(take)[self.filled : self.filled + take] = data[pos : pos + take]
                self.filled += take
                pos += take
                self.complete()
                continue
            if not self.header and size - pos >= 5:  # the prefix here whole: the common case
                flag, length = data[pos], int.from_bytes(data[pos + 1 : pos + 5], "big")
                pos += 5
            else:
                take = min(size - pos, 5 - len(self.header))
                self.header += data[pos : pos + take]
                pos += take
                if len(self.header) < 5:
                    return
                flag, length = self.header[0], int.from_bytes(self.header[1:5], "big")
                self.header.clear()
            if not self._allowed(flag, length):
                return
            if size - pos >= length and length < self._budget.minimum:
                self.deliver(data[pos : pos + length].tobytes())
                pos += length
            elif not length:
                self.deliver(b"")
            else:
                ahead = self._budget.ahead(length)
                self.body, self.length, self.filled = new_body(ahead), length, 0
                self._budget.used += ahead

    def room(self, coming: int) -> Body:
        """The body being received, grown (doubling, up to its length) to hold `coming` more bytes."""
        body = self.body
        assert body is not None
        need = self.filled + coming
        if len(body) < need:
            grown = new_body(min(self.length, max(need, 2 * len(body))))
            grown[: self.filled] = body[: self.filled]
            self._budget.used += len(grown) - len(body)
            self.body = body = grown
        return body

    def complete(self) -> None:
        """Deliver the body being received once it is whole."""
        body = self.body
        if body is not None and self.filled == self.length:
            self._budget.used -= len(body)
            self.body = None
            self.deliver(body.data.toreadonly())

    def _allowed(self, flag: int, length: int) -> bool:
        if flag:
            failure = Aborted(
                grpc.StatusCode.UNIMPLEMENTED, "compressed gRPC messages are not accepted: send them uncompressed"
            )
        elif length > self._budget.max_message:
            failure = Aborted(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"a message of {length} bytes is over this depot's limit of {self._budget.max_message} "
                "(FLEET_MAX_MESSAGE_SIZE)",
            )
        else:
            return True
        self.fail(failure)
        self.dropping = True  # the rest of the stream is dropped
        return False

    def end(self) -> None:
        if self.dropping:
            return
        if self.body is not None or self.header:
            self.fail(Aborted(grpc.StatusCode.INTERNAL, "the stream ended in the middle of a message"))
        self.ended = True
        self._wake()

    def discard(self) -> int:
        """The stream is done with: drop what the handler has not taken, and all that may come
        after; how many bytes were dropped."""
        self.dropping = True
        if self.body is not None:
            self._budget.used -= len(self.body)
        self.body = None
        self.header.clear()
        dropped = sum(len(request) for request in self._queue)
        self._queue.clear()
        return dropped

    def fail(self, failure: Aborted) -> None:
        if self._failure is None:
            self._failure = failure
        self._wake()

    def _wake(self) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_result(None)


WriteHandler = Callable[[AsyncIterator[bytes], WriteCall], Awaitable[Any]]
