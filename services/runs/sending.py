"""Large response bodies handed to the HTTP server in slices.

A download's pieces are as large as its reads (16 MiB from the warm store). Handed whole to the
server, each one is written to the socket as far as the socket takes it, and the rest is copied
twice on the event loop (sliced off, then into the transport's buffer) while nothing else runs:
with 16 MiB pieces that was most of the loop's time in a whole download. In slices of about what a
socket takes at once, each goes to the kernel as it is, a view of the piece, never copied."""

from __future__ import annotations

from collections.abc import AsyncIterable, AsyncIterator, Iterable

from starlette.concurrency import iterate_in_threadpool

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
