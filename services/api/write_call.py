"""One WriteMessages stream served by the front (`h2_writes`), as its handler sees it.

The handler is the one gRPC calls (`MessageProxy.write_messages`); a `WriteCall` has the few methods
of `grpc.aio.ServicerContext` it uses, and gives it the stream's requests in the order they came.
"""

from __future__ import annotations

import asyncio
import collections
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, NoReturn

import grpc


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


class WriteCall:
    """The requests of one stream, fed by its connection, and what the handler says of its answer."""

    def __init__(
        self, stream_id: int, metadata: tuple[tuple[str, Any], ...], taken: Callable[[int, int], None]
    ) -> None:
        self.stream_id, self._metadata = stream_id, metadata
        self._taken = taken  # told how many bytes the handler took, for the connection's back-pressure
        self._queue: collections.deque[bytes | memoryview] = collections.deque()
        self._waiter: asyncio.Future[None] | None = None
        self._failure: Aborted | None = None
        self.ended = False  # the client sent the end of its requests
        self.dropping = False  # what more the client sends is dropped (the stream failed or was answered)
        self.trailing: tuple[tuple[str, str], ...] = ()
        # the message being put together: its 5-byte prefix (while split over frames), then its body
        self.header = bytearray()
        self.body: bytearray | None = None
        self.length = 0  # the body's, as its prefix declares
        self.filled = 0

    # --- what the handler calls (grpc.aio.ServicerContext's names) --------------------------

    def invocation_metadata(self) -> tuple[tuple[str, Any], ...]:
        return self._metadata

    def set_trailing_metadata(self, metadata: tuple[tuple[str, str], ...]) -> None:
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
        self._taken(self.stream_id, len(request))
        return request

    async def requests(self) -> AsyncIterator[bytes]:
        while (request := await self.read()) is not grpc.aio.EOF:
            yield request

    # --- what the connection calls ----------------------------------------------------------

    def deliver(self, request: bytes | memoryview) -> None:
        self._queue.append(request)
        self._wake()

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
