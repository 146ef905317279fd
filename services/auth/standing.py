"""Streams that outlive the request that opened them (a live run followed over HTTP, a
`ReadMessages` reader): what their token or signed link granted is checked again while they run, at
least every `RECHECK_S` and at the moment it expires, so revoking the token or reaching the expiry
ends the stream as it would refuse a new request.

The check asks the auth module's own lookup of the token's record (`Auth.standing`: cached for
`FLEET_AUTH_CACHE_S`, so a revocation on another node is seen within that plus `RECHECK_S`)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncGenerator, AsyncIterator

import sqlalchemy as sa

from core.clock import iso_utc
from core.errors import UnauthenticatedError, UnavailableError
from services.auth.scopes import Principal
from services.auth.tokens import EXPIRED, REVOKED, Auth

log = logging.getLogger(__name__)

# A stream's grant is checked at least this often (and at its expiry). A check costs a lookup in
# the auth module's cache; the catalog is asked at most every FLEET_AUTH_CACHE_S per token.
RECHECK_S = 1.0
LINK = "link"  # the surface of signed links: their streams end with words about the link


def grant_ended(auth: Auth, principal: Principal, surface: str) -> UnauthenticatedError | None:
    """Why what `principal` was granted has ended since its request was let in (its token revoked or
    expired, its link expired), counted as a refusal of `surface`; None while it holds, and always
    with auth off or for a node's own token. May ask the catalog: call off the event loop."""
    if not auth.enabled or principal.token_id is None:
        return None
    ended = _why_ended(auth, principal, surface == LINK)
    if ended is not None:
        auth.refused(surface, ended.reason)
    return ended


def _why_ended(auth: Auth, principal: Principal, by_link: bool) -> UnauthenticatedError | None:
    now = auth.clock()
    if principal.expires_at is not None and principal.expires_at <= now:  # known here: no lookup
        what = "this link" if by_link else f"token {principal.token_id}"
        return UnauthenticatedError(f"{what} expired at {iso_utc(principal.expires_at)}: ask for a new one", EXPIRED)
    assert principal.token_id is not None
    record = auth.standing(principal.token_id)
    if record is None or record.revoked_at is not None:
        what = "the token that signed this link" if by_link else f"token {principal.token_id}"
        return UnauthenticatedError(f"{what} was revoked: ask for a new one", REVOKED)
    return None


class GrantWatch:
    """The grant of one long stream, checked again as it runs (see `grant_ended`)."""

    def __init__(self, auth: Auth, principal: Principal, surface: str, every_s: float = RECHECK_S) -> None:
        self.auth, self.principal, self.surface, self.every_s = auth, principal, surface, every_s
        self.watched = auth.enabled and principal.token_id is not None
        self._checked_at = time.monotonic()

    def wait_s(self) -> float | None:
        """How long the stream may wait for what it sends next before its grant is due to be checked
        again; None if it never is (auth off)."""
        if not self.watched:
            return None
        due = self._checked_at + self.every_s - time.monotonic()
        if self.principal.expires_at is not None:
            due = min(due, (self.principal.expires_at - self.auth.clock()).total_seconds())
        return max(0.0, due)

    async def ended(self) -> UnauthenticatedError | None:
        """Why the stream must end now, if its grant is due to be checked and has ended; else None.
        A catalog that does not answer ends nothing (the expiry is still checked: it needs none)."""
        wait = self.wait_s()
        if wait is None or wait > 0:
            return None
        self._checked_at = time.monotonic()
        try:
            return await asyncio.to_thread(grant_ended, self.auth, self.principal, self.surface)
        except (sa.exc.SQLAlchemyError, UnavailableError) as exc:
            log.warning("could not check token %s of a stream (%s): it goes on", self.principal.token_id, exc)
            return None


async def while_granted(watch: GrantWatch, pieces: AsyncIterator[bytes], closing: bytes = b"") -> AsyncIterator[bytes]:
    """`pieces` as they come, until they end or the grant does (`watch`, checked between pieces and
    while waiting for one): then `closing` (the format's own end, so the client sees a stream that
    ended rather than one cut off) if anything was sent, and nothing more. `pieces` is closed
    either way."""
    pending: asyncio.Future[bytes] | None = None
    sent = False
    try:
        while True:
            if pending is None:
                pending = asyncio.ensure_future(anext(pieces))
            done, _ = await asyncio.wait({pending}, timeout=watch.wait_s())
            ended = await watch.ended()
            if ended is not None:
                log.info("a stream of %s ended: %s", watch.principal.subject, ended.message)
                if sent and closing:
                    yield closing
                return
            if not done:
                continue
            try:
                piece = pending.result()
            except StopAsyncIteration:
                pending = None
                return
            pending = None
            yield piece
            sent = True
    finally:
        if pending is not None:
            pending.cancel()
            with contextlib.suppress(asyncio.CancelledError, StopAsyncIteration, Exception):
                await pending
        if isinstance(pieces, AsyncGenerator):
            await pieces.aclose()
