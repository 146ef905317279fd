"""The REST port's protocol splices a response's body into the client's connection when an app asks
(`services.storage.splice.SPLICE_EXTENSION`): offered on plain TCP, the spliced bytes follow those
sent before them on the socket, the connection serves its next request after, a source that ends
early cuts the response (never a body that claims more than it holds), a client that leaves ends
the splice quietly, and an app that does not ask is served as before."""

from __future__ import annotations

import asyncio
import os
import socket
import threading
from collections.abc import MutableMapping
from typing import Any

import httpx
import pytest

from services.storage.splice import SPLICE_EXTENSION, SPLICE_MESSAGE, SourceEnded
from tests.services.api.served import served
from tests.waiting import wait_for

LEADING = b"lead:"


class SplicingApp:
    """GET /?n=N&cut=K: LEADING through the body, then N bytes spliced from a socket a thread fills
    (and closes after K bytes, if K is given). Records each request's scope and outcome."""

    def __init__(self) -> None:
        self.scopes: list[MutableMapping[str, Any]] = []
        self.outcomes: list[str] = []
        self.sent: dict[int, bytes] = {}

    async def __call__(self, scope: MutableMapping[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return
        self.scopes.append(scope)
        query = dict(part.split("=") for part in scope["query_string"].decode().split("&") if part)
        n = int(query.get("n", "0"))
        cut = int(query["cut"]) if "cut" in query else None
        payload = os.urandom(n)
        self.sent[len(self.scopes)] = LEADING + payload
        headers = [(b"content-length", str(len(LEADING) + n).encode())]
        await send({"type": "http.response.start", "status": 200, "headers": headers})
        await send({"type": "http.response.body", "body": LEADING, "more_body": True})
        if SPLICE_EXTENSION not in scope.get("extensions", {}):
            await send({"type": "http.response.body", "body": payload})
            self.outcomes.append("streamed")
            return
        feeder, source = socket.socketpair()
        source.setblocking(False)
        thread = threading.Thread(target=_feed, args=(feeder, payload[:cut] if cut is not None else payload))
        thread.start()
        try:
            await send({"type": SPLICE_MESSAGE, "fd": source.fileno(), "count": n, "stall_s": 30})
            await send({"type": "http.response.body", "body": b""})
            self.outcomes.append("spliced")
        except SourceEnded as exc:
            self.outcomes.append(f"source ended after {exc.moved}")
            raise
        finally:
            source.close()  # a feeder still writing (its reader gone) stops
            await asyncio.to_thread(thread.join)


def _feed(sock: socket.socket, data: bytes) -> None:
    try:
        sock.sendall(data)
    except OSError:
        pass  # the reader went away
    finally:
        sock.close()


def test_a_spliced_body_follows_what_was_sent_before_it_and_the_connection_goes_on():
    app = SplicingApp()
    with served(app) as url, httpx.Client(base_url=url) as client:
        for n in (0, 1, 3_000_000, 10_000):
            response = client.get("/", params={"n": n})
            assert response.status_code == 200 and response.content == app.sent[len(app.scopes)]
        assert app.outcomes == ["spliced"] * 4
        assert len({scope["client"] for scope in app.scopes}) == 1  # one connection, kept alive


def test_a_source_that_ends_early_cuts_the_response_and_the_server_goes_on():
    app = SplicingApp()
    with served(app) as url:
        with pytest.raises(httpx.RemoteProtocolError):
            httpx.get(f"{url}/", params={"n": 2_000_000, "cut": 500_000})
        assert app.outcomes == ["source ended after 500000"]
        response = httpx.get(f"{url}/", params={"n": 1000})
        assert response.content == app.sent[2]


def test_a_client_that_leaves_ends_the_splice_quietly(caplog: pytest.LogCaptureFixture):
    app = SplicingApp()
    with served(app) as url:
        port = int(url.rsplit(":", 1)[1])
        with socket.create_connection(("127.0.0.1", port)) as sock:
            sock.sendall(b"GET /?n=50000000 HTTP/1.1\r\nHost: depot\r\n\r\n")
            sock.recv(65536)  # the head and the first bytes, then gone
        wait_for(lambda: app.outcomes, timeout=30, what="the splice to end")
        assert app.outcomes == ["spliced"]  # the rest dropped, as for a streamed body; no error
        assert httpx.get(f"{url}/", params={"n": 10}).content == app.sent[2]
    assert not [r for r in caplog.records if r.levelname == "ERROR"]


def test_without_the_extension_the_app_streams_as_before():
    """A request the server cannot splice into (here: the app under httpx's in-process transport,
    which offers no extension) gets the same bytes by the body."""
    app = SplicingApp()
    transport = httpx.ASGITransport(app=app)

    async def get() -> httpx.Response:
        async with httpx.AsyncClient(transport=transport, base_url="http://depot") as client:
            return await client.get("/", params={"n": 100_000})

    response = asyncio.run(get())
    assert response.content == app.sent[1] and app.outcomes == ["streamed"]
