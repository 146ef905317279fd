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
from typing import TypeVar

T = TypeVar("T")

NOTHING_TOLERATED: tuple[type[BaseException], ...] = ()


class WaitTimeout(AssertionError):
    """The condition did not hold in time; an AssertionError so pytest reports it as a failure."""


class _LastSeen:
    """What the condition last answered, for the failure message."""

    def __init__(self) -> None:
        self.said = "never asked"

    def value(self, value: object) -> None:
        self.said = f"last returned {value!r}"

    def raised(self, exc: BaseException) -> None:
        self.said = f"last raised {type(exc).__name__}: {exc}"


def _ask(condition: Callable[[], T | None], tolerate: tuple[type[BaseException], ...], last: _LastSeen) -> T | None:
    try:
        value = condition()
    except tolerate as exc:
        last.raised(exc)
        return None
    last.value(value)
    return value


def _timed_out(what: str, timeout: float, last: _LastSeen, detail: Callable[[], str] | None) -> WaitTimeout:
    more = f"\n{detail()}" if detail is not None else ""
    return WaitTimeout(f"waited {timeout:g} s for {what}; {last.said}{more}")


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
    deadline = time.monotonic() + timeout
    last = _LastSeen()
    while True:
        value = _ask(condition, tolerate, last)
        if value:
            return value
        if time.monotonic() > deadline:
            raise _timed_out(what, timeout, last, detail)
        time.sleep(interval)


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
    deadline = time.monotonic() + timeout
    last = _LastSeen()
    while True:
        value = _ask(condition, NOTHING_TOLERATED, last)
        if value:
            return value
        if time.monotonic() > deadline:
            raise _timed_out(what, timeout, last, None)
        await asyncio.sleep(interval)
