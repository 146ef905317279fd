"""Per-token rate limits on costly reads (SQL, downloads): a moving window per token and kind, in
this process's memory (each node counts its own)."""

from __future__ import annotations

import math
import time

from limits import RateLimitItem, parse, storage, strategies

from core.errors import RateLimitedError
from services.auth.scopes import Principal


class RateLimits:
    def __init__(self, rates: dict[str, str]) -> None:
        self._limiter = strategies.MovingWindowRateLimiter(storage.MemoryStorage())
        self._rates: dict[str, RateLimitItem] = {kind: parse(rate) for kind, rate in rates.items()}

    def hit(self, kind: str, principal: Principal) -> None:
        """Count one request of `kind`; 429 with Retry-After once the token used its share. Nothing is
        counted when auth is off (no token to count against)."""
        if principal.token_id is None:
            return
        rate = self._rates[kind]
        if self._limiter.hit(rate, kind, principal.rate_key):
            return
        reset = self._limiter.get_window_stats(rate, kind, principal.rate_key).reset_time
        retry = math.ceil(reset - time.time())
        raise RateLimitedError(
            f"too many {kind} requests with this token (at most {rate.amount} per {rate.multiples} "
            f"{rate.GRANULARITY.name}): retry in {max(1, retry)} s",
            retry,
        )
