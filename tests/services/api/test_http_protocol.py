"""The REST port's HTTP/1.1 protocol (`services.api.http_protocol`): a request's head over 64 KiB is
refused with 400 naming the bound and the connection closed, however it is sent (one endless header
included), while heads under it, keep-alive requests and bodies of any size go through; and
`fleet serve` runs it, with auth on."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn

from services.api.http_protocol import HEAD_LIMIT, HEAD_TOO_LARGE, BoundedHttpToolsProtocol
from tests.services.ingest.live_server import LiveServer

Receive = Callable[[], Awaitable[dict[str, Any]]]
Send = Callable[[dict[str, Any]], Awaitable[None]]


async def counting_app(scope: dict[str, Any], receive: Receive, send: Send) -> None:
    """Answers 200 with how many body bytes it read."""
    assert scope["type"] == "http"
    size, more = 0, True
    while more:
        message = await receive()
        size += len(message.get("body", b""))
        more = message.get("more_body", False)
    text = str(size).encode()
    headers = [(b"content-type", b"text/plain"), (b"content-length", str(len(text)).encode())]
    await send({"type": "http.response.start", "status": 200, "headers": headers})
    await send({"type": "http.response.body", "body": text})


@asynccontextmanager
async def serving() -> AsyncIterator[int]:
    """uvicorn with the bounded protocol on a free loopback port; yields the port."""
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    config = uvicorn.Config(counting_app, http=BoundedHttpToolsProtocol, lifespan="off", log_level="warning")
    server = uvicorn.Server(config)
    task = asyncio.create_task(server.serve(sockets=[listener]))
    while not server.started:
        await asyncio.sleep(0.01)
    try:
        yield listener.getsockname()[1]
    finally:
        server.should_exit = True
        await task


def request(headers_bytes: int, body: bytes = b"") -> bytes:
    """A request whose head is about `headers_bytes` long (one long header), with `body`."""
    filler = b"x" * max(0, headers_bytes - 100)
    return b"POST /echo HTTP/1.1\r\nHost: depot\r\nX-Filler: %s\r\nContent-Length: %d\r\n\r\n%s" % (
        filler,
        len(body),
        body,
    )


async def answer(reader: asyncio.StreamReader) -> tuple[int, bytes]:
    head = await reader.readuntil(b"\r\n\r\n")
    status = int(head.split(b" ", 2)[1])
    lines = head.split(b"\r\n")
    length = next(int(line.split(b":")[1]) for line in lines if line.lower().startswith(b"content-length"))
    return status, await reader.readexactly(length)


def exchange(*requests: bytes) -> list[tuple[int, bytes]]:
    """The answers to `requests` sent one after another on one connection."""

    async def main() -> list[tuple[int, bytes]]:
        async with serving() as port:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            answers = []
            for sent in requests:
                writer.write(sent)
                await writer.drain()
                answers.append(await answer(reader))
            writer.close()
            return answers

    return asyncio.run(main())


def test_heads_under_the_bound_and_bodies_of_any_size_go_through_on_one_connection():
    big_body = b"b" * (3 * 1024 * 1024)  # its first bytes arrive with the head: not counted as head
    answers = exchange(request(HEAD_LIMIT - 2048), request(HEAD_LIMIT - 2048, big_body), request(200, b"abc"))
    assert answers == [(200, b"0"), (200, str(len(big_body)).encode()), (200, b"3")]


def test_a_head_over_the_bound_is_refused_naming_it_and_the_connection_closed():
    async def main() -> tuple[int, bytes, bytes]:
        async with serving() as port:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(request(HEAD_LIMIT + 4096))
            await writer.drain()
            status, text = await answer(reader)
            rest = await reader.read()  # closed by the server: nothing more comes
            writer.close()
            return status, text, rest

    status, text, rest = asyncio.run(main())
    assert (status, text.decode(), rest) == (400, HEAD_TOO_LARGE, b"")
    assert f"{HEAD_LIMIT // 1024} KiB" in HEAD_TOO_LARGE


@pytest.mark.parametrize("after_a_request", [False, True], ids=["first", "kept-alive"])
def test_an_endless_header_is_cut_off_near_the_bound(after_a_request: bool):
    """A header that never ends, sent in small writes (as a connection's first request or after one
    answered on it): refused once the bound is passed, not read on."""

    async def main() -> tuple[int, int]:
        async with serving() as port:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            if after_a_request:
                writer.write(request(200, b"abc"))
                assert await answer(reader) == (200, b"3")
            writer.write(b"GET / HTTP/1.1\r\nHost: depot\r\nX-Endless: ")
            sent = 0
            refused = asyncio.ensure_future(answer(reader))
            while not refused.done() and sent < 64 * HEAD_LIMIT:
                writer.write(b"y" * 1024)
                sent += 1024
                try:
                    await writer.drain()
                except ConnectionError:
                    break
                await asyncio.sleep(0)
            status, _ = await asyncio.wait_for(refused, 10)
            writer.close()
            return status, sent

    status, sent = asyncio.run(main())
    assert status == 400
    assert sent < 8 * HEAD_LIMIT  # the server stopped it near the bound, not at the sender's limit


@pytest.mark.slow
def test_fleet_serve_refuses_an_oversized_head_with_auth_on(tmp_path: Path):
    server = LiveServer(tmp_path / "data", auth="on").start()
    try:
        fine = httpx.get(f"{server.url}/healthz", headers={"X-Filler": "x" * (HEAD_LIMIT // 2)}, timeout=10)
        assert fine.status_code == 200
        refused = httpx.get(f"{server.url}/v1/runs", headers={"X-Filler": "x" * (HEAD_LIMIT + 1024)}, timeout=10)
        assert (refused.status_code, refused.text) == (400, HEAD_TOO_LARGE)
        assert server.healthy()
    finally:
        server.stop()
