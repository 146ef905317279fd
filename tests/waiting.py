"""Waiting in a test for what another thread, task or process does: one poll loop for the suite.

A test that waits polls a condition until it holds, bounded by a timeout, and when the time runs
out says what it waited for and what it last saw, so that a failure on a loaded CI machine can be
read without running it again. Wrappers that know more (a server process that died, a viewer's
state) pass it in as `detail` or raise from the condition rather than writing the loop again.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Generic, TypeVar

T = TypeVar("T")

NOTHING_TOLERATED: tuple[type[BaseException], ...] = ()


class WaitTimeout(AssertionError):
    """The condition did not hold in time; an AssertionError so pytest reports it as a failure."""


class _Wait(Generic[T]):
    """One wait's state: the deadline and what the condition last answered, for the failure message."""

    def __init__(
        self,
        condition: Callable[[], T | None],
        timeout: float,
        what: str,
        tolerate: tuple[type[BaseException], ...],
        detail: Callable[[], str] | None,
    ) -> None:
        self.condition, self.timeout, self.what, self.tolerate, self.detail = condition, timeout, what, tolerate, detail
        self.deadline = time.monotonic() + timeout
        self.last = "never asked"

    def check(self) -> T | None:
        """The condition's value if it holds; None to ask again; WaitTimeout once the time is up."""
        try:
            value = self.condition()
        except self.tolerate as exc:
            value, self.last = None, f"last raised {type(exc).__name__}: {exc}"
        else:
            self.last = f"last returned {value!r}"
        if value:
            return value
        if time.monotonic() > self.deadline:
            more = f"\n{self.detail()}" if self.detail is not None else ""
            raise WaitTimeout(f"waited {self.timeout:g} s for {self.what}; {self.last}{more}")
        return None


def wait_for(
    condition: Callable[[], T | None],
    timeout: float,
    what: str,
    *,
    interval: float = 0.1,
    tolerate: tuple[type[BaseException], ...] = NOTHING_TOLERATED,
    detail: Callable[[], str] | None = None,
) -> T:
    """Poll `condition` every `interval` seconds until it returns something truthy, and return that.

    After `timeout` seconds fail with WaitTimeout naming `what`, the condition's last value or
    tolerated exception, and `detail()` when given. An exception of a type in `tolerate` counts as
    "not yet" (a page still changing); any other propagates at once, which is how a condition says
    that waiting longer is pointless (the process it waits on has exited).
    """
    wait = _Wait(condition, timeout, what, tolerate, detail)
    while (value := wait.check()) is None:
        time.sleep(interval)
    return value


def holds_within(condition: Callable[[], object], timeout: float, *, interval: float = 0.1) -> bool:
    """Whether `condition` came to hold within `timeout` seconds, for a caller that reports it itself."""
    try:
        wait_for(condition, timeout, "the condition", interval=interval)
    except WaitTimeout:
        return False
    return True


async def wait_for_async(
    condition: Callable[[], T | None],
    timeout: float,
    what: str,
    *,
    interval: float = 0.01,
) -> T:
    """`wait_for` inside an event loop: polls without blocking the tasks that make the condition hold."""
    wait = _Wait(condition, timeout, what, NOTHING_TOLERATED, None)
    while (value := wait.check()) is None:
        await asyncio.sleep(interval)
    return value
