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

from typing import Any

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

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

    def on_headers_complete(self) -> None:
        self.in_head, self.read_in_head = False, 0
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self.in_head = True  # the next request on this connection (keep-alive)
