"""Large response bodies handed to the HTTP server in slices.

A download's pieces are as large as its reads (16 MiB from the warm store). Handed whole to the
server, each one is written to the socket as far as the socket takes it, and the rest is copied
twice on the event loop (sliced off, then into the transport's buffer) while nothing else runs:
with 16 MiB pieces that was most of the loop's time in a whole download. In slices of about what a
socket takes at once, each goes to the kernel as it is, a view of the piece, never copied."""

from __future__ import annotations

from collections.abc import AsyncIterable, AsyncIterator, Iterable, Mapping

from starlette.concurrency import iterate_in_threadpool
from starlette.responses import StreamingResponse
from starlette.types import Receive, Scope, Send

from services.runs.sealed import WholeOnLoop
from services.storage.splice import SPLICE_EXTENSION, SPLICE_MESSAGE, Source

SEND_BYTES = 1 << 20  # about what a loopback or LAN socket's send buffer takes in one call


async def in_slices(
    body: Iterable[bytes | memoryview] | AsyncIterable[bytes | memoryview], size: int = SEND_BYTES
) -> AsyncIterator[bytes | memoryview]:
    """`body`'s bytes in the same order, no piece longer than `size` (a synchronous body is read
    off the event loop, a piece at a time, as the server would read it)."""
    pieces = body if isinstance(body, AsyncIterable) else iterate_in_threadpool(body)
    async for piece in pieces:
        if len(piece) <= size:
            yield piece
            continue
        view = memoryview(piece)
        for start in range(0, len(view), size):
            yield view[start : start + size]


class WholeObjectResponse(StreamingResponse):
    """A sealed object sent whole. Where the server offers to splice into the client's connection
    (the ASGI extension `SPLICE_EXTENSION`: the REST port's protocol, on a plain TCP connection)
    and the store's answers can be handed over, the kernel moves the object from the store's socket
    to the client's and the body never passes through Python; otherwise it is streamed in slices."""

    def __init__(self, whole: WholeOnLoop, headers: Mapping[str, str]) -> None:
        super().__init__(in_slices(whole), media_type="application/octet-stream", headers=headers)
        self.whole = whole
        self.spliced = False  # whether this answer goes by splice: decided per request, in __call__

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        self.spliced = SPLICE_EXTENSION in scope.get("extensions", {}) and self.whole.splices()
        await super().__call__(scope, receive, send)

    async def stream_response(self, send: Send) -> None:
        if not self.spliced:
            await super().stream_response(send)
            return
        await send({"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers})

        async def write(data: bytes) -> None:
            await send({"type": "http.response.body", "body": data, "more_body": True})

        async def splice(source: Source) -> None:
            await send({"type": SPLICE_MESSAGE, "fd": source.fd, "count": source.left, "stall_s": source.stall_s})

        await self.whole.send_by_splice(write, splice)
        await send({"type": "http.response.body", "body": b"", "more_body": False})
