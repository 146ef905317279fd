"""A stream that outlives its request stops when what let it in ends: its token revoked, its token
or link expired; checked while it sends and while it waits, on tokens listed in DuckDB and Postgres."""

from __future__ import annotations

import asyncio
import datetime as dt
import time
from collections.abc import AsyncIterator
from dataclasses import replace

import pytest

from core.clock import utcnow
from services.auth.scopes import Principal
from services.auth.standing import LINK, GrantWatch, grant_ended, while_granted
from services.auth.tokens import EXPIRED, REVOKED, Auth

EVERY_S = 0.05  # how often the tests' watches look at the token


def reader(auth: Auth) -> Principal:
    issued = auth.issue(subject="viewer", scopes=["read"], created_by="test")
    return auth.authenticate(issued.token, "rest")


def test_a_grant_holds_until_its_token_is_revoked(auth: Auth):
    principal = reader(auth)
    assert grant_ended(auth, principal, "rest") is None
    assert principal.token_id is not None
    auth.revoke(principal.token_id, "admin")
    ended = grant_ended(auth, principal, "rest")
    assert ended is not None and ended.reason == REVOKED and principal.token_id in ended.message
    assert auth.failures[("rest", REVOKED)] == 1


def test_a_links_grant_ends_at_its_expiry_without_asking_the_catalog(auth: Auth):
    principal = replace(reader(auth), expires_at=utcnow() - dt.timedelta(seconds=1))
    auth.catalog = None  # nothing to ask: the expiry is known
    ended = grant_ended(auth, principal, LINK)
    assert ended is not None and ended.reason == EXPIRED and "this link expired" in ended.message


def test_with_auth_off_nothing_ends():
    off = Auth(enabled=False, keys=None, catalog=None)
    principal = off.authenticate(None, "rest")
    assert grant_ended(off, principal, "rest") is None
    assert not GrantWatch(off, principal, "rest").watched and GrantWatch(off, principal, "rest").wait_s() is None


class Pieces:
    """An endless stream: a piece every `gap_s` (never, after the first, with None), and whether it
    was closed."""

    def __init__(self, gap_s: float | None) -> None:
        self.gap_s, self.sent, self.closed = gap_s, 0, False

    async def stream(self) -> AsyncIterator[bytes]:
        try:
            while True:
                yield b"x" * 1000
                self.sent += 1
                await asyncio.sleep(self.gap_s if self.gap_s is not None else 3600)
        finally:
            self.closed = True


async def drain(stream: AsyncIterator[bytes], on_first: object = None) -> tuple[bytes, float]:
    """Everything `stream` sends, and how long after its first piece it ended."""
    received, first = b"", None
    async for piece in stream:
        received += piece
        if first is None:
            first = time.monotonic()
            if callable(on_first):
                await asyncio.to_thread(on_first)
    assert first is not None
    return received, time.monotonic() - first


@pytest.mark.parametrize("gap_s", [0.001, None], ids=["busy", "quiet"])
def test_a_stream_ends_with_its_closing_once_its_token_is_revoked(auth: Auth, gap_s: float | None):
    principal = reader(auth)
    pieces = Pieces(gap_s)
    watch = GrantWatch(auth, principal, "rest", every_s=EVERY_S)
    assert principal.token_id is not None
    token_id = principal.token_id

    received, took = asyncio.run(
        drain(while_granted(watch, pieces.stream(), closing=b"END"), lambda: auth.revoke(token_id, "admin"))
    )
    assert received.endswith(b"END") and received.count(b"END") == 1
    assert took < 5.0  # a few checks, however busy or quiet the stream; without them: never
    assert pieces.closed
    sent_after = pieces.sent
    assert len(received) - 3 <= (sent_after + 1) * 1000  # nothing sent after the end but the closing


def test_a_stream_ends_at_its_links_expiry(auth: Auth):
    principal = replace(reader(auth), expires_at=utcnow() + dt.timedelta(seconds=0.5))
    pieces = Pieces(0.01)
    watch = GrantWatch(auth, principal, LINK, every_s=3600)  # the expiry is waited for, not polled

    received, _ = asyncio.run(drain(while_granted(watch, pieces.stream(), closing=b"END")))
    assert utcnow() >= principal.expires_at  # type: ignore[operator]
    assert utcnow() - principal.expires_at < dt.timedelta(seconds=2)  # type: ignore[operator]
    assert received.endswith(b"END") and pieces.closed
    assert auth.failures[(LINK, EXPIRED)] == 1


def test_a_stream_that_ends_by_itself_ends_as_it_is(auth: Auth):
    async def three() -> AsyncIterator[bytes]:
        for piece in (b"a", b"b", b"c"):
            yield piece

    watch = GrantWatch(auth, reader(auth), "rest", every_s=EVERY_S)

    async def run() -> bytes:
        return b"".join([p async for p in while_granted(watch, three(), closing=b"END")])

    assert asyncio.run(run()) == b"abc"


def test_a_client_that_goes_away_closes_the_stream(auth: Auth):
    pieces = Pieces(None)
    watch = GrantWatch(auth, reader(auth), "rest", every_s=EVERY_S)

    async def read_one_and_leave() -> None:
        stream = while_granted(watch, pieces.stream())
        assert isinstance(stream, AsyncIterator)
        await anext(stream)
        waiting = asyncio.ensure_future(anext(stream))  # waits for a piece that never comes
        await asyncio.sleep(3 * EVERY_S)  # a few checks pass while it waits: the token still holds
        assert not waiting.done()
        waiting.cancel()  # the client went away
        with pytest.raises(asyncio.CancelledError):
            await waiting

    asyncio.run(read_one_and_leave())
    assert pieces.closed
