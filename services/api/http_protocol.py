"""The REST port's HTTP/1.1 protocol: uvicorn's httptools one, with a bound on a request's head.

Why httptools: h11, uvicorn's other parser, copies every piece of a body it sends (it joins what it
writes into new bytes), 17 % of the server's CPU in a whole warm download (BENCHMARKS.md); the
httptools protocol writes the piece as given. Why a bound: uvicorn puts none on a request's head
with httptools (h11 refuses a head still incomplete past 16 KiB), and httptools gathers a header's
name and value before it hands them over, so a client could send one endless header and the server
would keep it all. 64 KiB leaves room for a long query string (a thousand entity filters is 20 KB:
the API itself names what is too many).

Two counts, each refusing past HEAD_LIMIT with 400 naming the bound, the connection closed: the
request line and headers as the parser hands them over (a whole head that is too long), and the
bytes read while a head is still incomplete (one that never ends: what a client can make the server
hold for a head is HEAD_LIMIT and one read more).
"""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Awaitable, Callable
from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol, RequestResponseCycle

from services.storage.splice import SPLICE_EXTENSION, SPLICE_MESSAGE, DestinationFailed, SourceEnded, splice_exactly

HEAD_LIMIT = 64 * 1024  # a request line and headers longer than this are refused
HEAD_TOO_LARGE = (
    f"the request's line and headers are over {HEAD_LIMIT // 1024} KiB: send fewer or shorter headers "
    "(a token goes in Authorization, filters in the query string or the body)"
)


class HeadTooLarge(Exception):
    """Raised in a parser callback: the parser stops, and uvicorn answers 400 (with HEAD_TOO_LARGE)."""


class BoundedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol refusing a request whose head is over HEAD_LIMIT bytes."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.in_head = True  # reading a request's line and headers (from the connection's first byte)
        self.read_in_head = 0  # bytes read while the head is incomplete
        self.head_size = 0  # of the request line and headers handed over so far
        self.too_large = False

    def data_received(self, data: bytes) -> None:
        counted = self.in_head
        if counted:
            self.read_in_head += len(data)
        super().data_received(data)
        # After the parser has read it: a read that completes the head is left to the precise count.
        if counted and self.in_head and self.read_in_head > HEAD_LIMIT and not self.transport.is_closing():
            self.too_large = True
            self.send_400_response(HEAD_TOO_LARGE)

    def send_400_response(self, msg: str) -> None:
        if self.too_large:
            self.logger.warning("refused a request whose head is over %d bytes", HEAD_LIMIT)
        super().send_400_response(HEAD_TOO_LARGE if self.too_large else msg)

    def _count(self, size: int) -> None:
        self.head_size += size
        if self.head_size > HEAD_LIMIT:
            self.too_large = True
            raise HeadTooLarge

    def on_message_begin(self) -> None:
        self.head_size = 0
        super().on_message_begin()

    def on_url(self, url: bytes) -> None:
        self._count(len(url) + 16)  # with the method and version around it
        super().on_url(url)

    def on_header(self, name: bytes, value: bytes) -> None:
        self._count(len(name) + len(value) + 4)  # ": " and CRLF
        super().on_header(name, value)

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        sock = transport.get_extra_info("socket")
        # splice(2) moves bytes as they are: not into a TLS connection, whose bytes Python encrypts
        self.splices = (
            sock is not None
            and transport.get_extra_info("sslcontext") is None
            and sock.family in (socket.AF_INET, socket.AF_INET6, socket.AF_UNIX)
        )

    def on_headers_complete(self) -> None:
        self.in_head, self.read_in_head = False, 0
        if self.splices:
            self.scope.setdefault("extensions", {})[SPLICE_EXTENSION] = {}
        before = self.cycle
        super().on_headers_complete()
        if self.splices and self.cycle is not None and self.cycle is not before:
            self.cycle.send = _splicing(self.cycle, self.cycle.send)  # type: ignore[method-assign,assignment]

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self.in_head = True  # the next request on this connection (keep-alive)


def _splicing(cycle: RequestResponseCycle, send: Callable[[Any], Awaitable[None]]) -> Callable[[Any], Awaitable[None]]:
    """`cycle`'s ASGI send, also taking SPLICE_MESSAGE: `count` bytes of the response's body moved
    by the kernel from the socket `fd` to the client's, given up if `fd` is silent for `stall_s`
    (services/storage/splice.py)."""

    async def splicing_send(message: Any) -> None:
        if message["type"] != SPLICE_MESSAGE:
            await send(message)
            return
        count = int(message["count"])
        if not cycle.response_started or cycle.response_complete or cycle.chunked_encoding is not False:
            raise RuntimeError("a spliced body needs a response started with a Content-Length")
        if count > cycle.expected_content_length:
            raise RuntimeError("Response content longer than Content-Length")
        if cycle.disconnected or cycle.scope["method"] == "HEAD":
            return
        await _drained(cycle)
        if cycle.disconnected:
            return
        client = cycle.transport.get_extra_info("socket")
        try:
            await splice_exactly(int(message["fd"]), client.fileno(), count, float(message["stall_s"]))
        except SourceEnded as exc:
            cycle.expected_content_length -= exc.moved
            raise
        except DestinationFailed:  # the client went away: the rest of the response is dropped, as uvicorn does
            cycle.disconnected = True
            cycle.transport.close()
            return
        cycle.expected_content_length -= count

    return splicing_send


async def _drained(cycle: RequestResponseCycle) -> None:
    """Wait until the transport holds nothing unsent (the response's head, usually sent at once), so
    that the spliced bytes follow it on the socket."""
    transport = cycle.transport
    if transport.get_write_buffer_size() == 0:
        return
    low, high = transport.get_write_buffer_limits()
    transport.set_write_buffer_limits(high=0)  # the protocol is paused now, and resumed once it is empty
    try:
        await cycle.flow.drain()
    finally:
        transport.set_write_buffer_limits(high=high, low=low)
