"""The one backoff policy: how long to wait after the n-th failure in a row. Its callers keep their
own state (a count per run, a count per link) because each is a "when may the next attempt start"
driven by a scheduler or a sender's loop, not a retry loop around one call; what they share is the
curve, so that promotion, catalog writes and the agent's link back off alike."""

from __future__ import annotations

import random
from collections.abc import Callable

JITTER = 0.2  # +-20 %: many agents cut off together do not all come back on the same tick


def backoff_delay(failures: int, *, first: float, cap: float) -> float:
    """The wait after `failures` failures in a row (1: `first`), doubling with each one, never
    more than `cap`; none before the first failure."""
    if failures < 1:
        return 0.0
    # The exponent stops growing once the cap is certainly reached, so no count overflows a float.
    return min(first * 2.0 ** min(failures - 1, 64), cap)


def jittered(delay: float, spread: float = JITTER, uniform: Callable[[float, float], float] = random.uniform) -> float:
    """`delay` moved at random by up to `spread` of itself either way."""
    return delay * uniform(1 - spread, 1 + spread)
