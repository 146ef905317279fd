"""Token records as the catalog last gave them, so that checking a token does not need the catalog
on the hot path.

A record younger than `fresh_s` (FLEET_AUTH_CACHE_S) is used as is. An older one is asked of the
catalog again on a small pool of its own, waited for at most `wait_s`; if the catalog does not
answer (down, hung, past its deadline), the record last seen is still used while it is younger than
`stale_s` (FLEET_AUTH_STALE_S): a revocation made during a catalog outage takes effect within that
bound. A token the catalog never confirmed, or confirmed too long ago, is refused UNAVAILABLE (503),
never let in unchecked. One lookup per token at a time: while one is under way (a hung catalog),
later checks of that token do not wait for it. What is known is a cachetools `TTLCache`: a record
leaves it once it is too old to be used even stale, and at most `MAX_TOKENS` are held."""

from __future__ import annotations

import concurrent.futures
import logging
import threading
import time
from collections.abc import Callable

from cachetools import TTLCache

from catalog.tokens import TokenRecord
from core.errors import CATALOG_DOWN, CatalogUnavailableError

log = logging.getLogger(__name__)

WAIT_S = 2.0  # the longest a token check waits for the catalog before it uses what it knows
# A hung catalog holds at most this many lookup threads (daemons: they never hold up the process's
# exit); beyond them a token is checked against what is known, without asking.
LOOKUP_THREADS = 4
MAX_TOKENS = 100_000  # records held at most (the least recently used go first: asked again when used)


class TokenCache:
    def __init__(
        self,
        lookup: Callable[[str], TokenRecord | None],
        *,
        fresh_s: float,
        stale_s: float,
        wait_s: float = WAIT_S,
        max_tokens: int = MAX_TOKENS,
    ) -> None:
        self._lookup = lookup
        self.fresh_s, self.stale_s, self.wait_s = fresh_s, max(stale_s, fresh_s), wait_s
        # token id -> (asked at, record), dropped `stale_s` after it came: older, it could not be used even stale.
        self._known: TTLCache[str, tuple[float, TokenRecord | None]] = TTLCache(max_tokens, self.stale_s)
        self._pending: dict[str, concurrent.futures.Future[TokenRecord | None]] = {}
        self._lock = threading.Lock()

    def get(self, token_id: str) -> TokenRecord | None:
        """The token's record (None: the catalog does not list it). Blocks at most `wait_s`: call
        off the event loop. CatalogUnavailableError if the catalog cannot confirm it in time and
        what was last seen of it is older than `stale_s` (or nothing was)."""
        now = time.monotonic()
        with self._lock:
            known = self._known.get(token_id)
        if known is not None and now - known[0] < self.fresh_s:
            return known[1]
        future, waiting = self._ask(token_id, now)
        try:
            # A lookup already under way is not waited for when something is known: it is hung.
            return future.result(timeout=self.wait_s if waiting or known is None else 0)
        except (concurrent.futures.TimeoutError, *CATALOG_DOWN) as exc:
            return self._stale(token_id, known, now, exc)

    def _ask(self, token_id: str, now: float) -> tuple[concurrent.futures.Future[TokenRecord | None], bool]:
        """The lookup of `token_id` under way, or a new one (True) started now."""
        future: concurrent.futures.Future[TokenRecord | None] = concurrent.futures.Future()
        with self._lock:
            under_way = self._pending.get(token_id)
            if under_way is not None:
                return under_way, False
            if len(self._pending) >= LOOKUP_THREADS:
                future.set_exception(concurrent.futures.TimeoutError("every token lookup thread waits on the catalog"))
                return future, False
            self._pending[token_id] = future
        threading.Thread(target=self._run, args=(token_id, now, future), name="token-lookup", daemon=True).start()
        return future, True

    def _run(self, token_id: str, asked_at: float, future: concurrent.futures.Future[TokenRecord | None]) -> None:
        try:
            record = self._lookup(token_id)
        except BaseException as exc:  # handed to whoever waits for it
            with self._lock:
                self._pending.pop(token_id, None)
            future.set_exception(exc)
            return
        with self._lock:
            self._pending.pop(token_id, None)
            self._known[token_id] = (asked_at, record)
        future.set_result(record)

    def _stale(
        self, token_id: str, known: tuple[float, TokenRecord | None] | None, now: float, exc: BaseException
    ) -> TokenRecord | None:
        if known is not None and now - known[0] < self.stale_s:
            log.warning(
                "catalog did not confirm token %s (%s): using its record of %.0f s ago",
                token_id,
                type(exc).__name__,
                now - known[0],
            )
            return known[1]
        raise CatalogUnavailableError(
            "the catalog cannot confirm this token right now (it did not answer): retry in a moment"
        ) from exc

    def forget(self, token_id: str) -> None:
        """Drop what is known of a token (revoked here: seen at once on this node)."""
        with self._lock:
            self._known.pop(token_id, None)

    def clear(self) -> None:
        with self._lock:
            self._known.clear()
