"""The suite's one poll loop: it returns what the condition found, and a timeout says what it saw."""

from __future__ import annotations

import asyncio
import itertools

import pytest

from tests.waiting import WaitTimeout, holds_within, wait_for, wait_for_async


def test_returns_the_conditions_first_truthy_value():
    answers = iter([None, 0, "", "ready"])
    assert wait_for(lambda: next(answers), 5, "the answer", interval=0.001) == "ready"


def test_a_timeout_names_what_it_waited_for_and_the_last_value():
    counter = itertools.count()
    with pytest.raises(WaitTimeout, match=r"waited 0.05 s for the door to open; last returned False\nlog: closed"):
        wait_for(lambda: next(counter) < 0, 0.05, "the door to open", interval=0.01, detail=lambda: "log: closed")


def test_a_tolerated_exception_is_not_yet_and_is_reported():
    def flaky() -> bool:
        raise KeyError("row 7")

    with pytest.raises(WaitTimeout, match=r"last raised KeyError: 'row 7'"):
        wait_for(flaky, 0.05, "the row", interval=0.01, tolerate=(KeyError,))


def test_any_other_exception_ends_the_wait_at_once():
    def dead() -> bool:
        raise RuntimeError("the process exited")

    with pytest.raises(RuntimeError, match="exited"):
        wait_for(dead, 60, "the process", tolerate=(KeyError,))


def test_holds_within_says_whether_it_held():
    assert holds_within(lambda: True, 1)
    assert not holds_within(lambda: False, 0.05, interval=0.01)


def test_the_async_wait_lets_other_tasks_make_it_hold():
    async def scenario() -> str:
        box: list[str] = []
        asyncio.get_running_loop().call_later(0.02, box.append, "done")
        return await wait_for_async(lambda: box[0] if box else None, 5, "the callback")

    assert asyncio.run(scenario()) == "done"
