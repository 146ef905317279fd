"""Following a hot run waits on the run's changes, woken by appends and by the run's end (from the
event loop or another thread), not on a timer; a follower that goes away leaves nothing waiting."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncGenerator

import pytest

from services.hot import read
from services.hot.read import HotRecording, follow_sizes
from services.hot.store import Changes, HotRun, HotStore
from services.rrd.frames import DEFAULT_VERSION, MessageKind

WAKE_S = 5.0  # a woken follower answers well within this; the safety recheck is made far longer


@pytest.fixture(autouse=True)
def no_recheck(monkeypatch: pytest.MonkeyPatch) -> None:
    """Only a notification can wake a follower in these tests."""
    monkeypatch.setattr(read, "FOLLOW_RECHECK_S", 3600.0)
    monkeypatch.setattr(read, "FOLLOW_BATCH_S", 0.0)


class LiveRun:
    """A hot run and its live flag, as ingest shows them to readers."""

    def __init__(self, hot_store: HotStore, run_id: str) -> None:
        self.hot = hot_store.create(run_id, DEFAULT_VERSION)
        self.live = True

    def recording(self) -> HotRecording:
        return HotRecording(self.hot.path, self.hot.size, {}, lambda: (self.hot.size, self.live), self.hot.changes)

    def end(self) -> None:
        self.live = False
        self.hot.changes.notify()  # as ingest does when it closes a run


def append(run: HotRun, payload: bytes = b"x" * 100) -> int:
    run.append(MessageKind.ARROW_MSG, payload)
    return run.size


async def next_size(sizes: AsyncGenerator[int, None]) -> int:
    return await asyncio.wait_for(anext(sizes), WAKE_S)


def test_a_follower_sees_each_append_and_ends_when_the_run_ends(hot_store: HotStore):
    run = LiveRun(hot_store, "run-a")

    async def scenario() -> None:
        sizes = follow_sizes(run.recording())
        assert await next_size(sizes) == run.hot.size  # the run as it stands
        waiting = asyncio.create_task(next_size(sizes))
        while run.hot.changes.waiting == 0:  # the follower is waiting for the run
            await asyncio.sleep(0)
        grown = append(run.hot)
        assert await waiting == grown
        grown = append(run.hot)
        assert await next_size(sizes) == grown
        ending = asyncio.create_task(next_size(sizes))
        while run.hot.changes.waiting == 0:
            await asyncio.sleep(0)
        run.end()
        with pytest.raises(StopAsyncIteration):
            await ending
        assert run.hot.changes.waiting == 0

    asyncio.run(scenario())


def test_appends_and_the_end_from_another_thread_wake_the_follower(hot_store: HotStore):
    run = LiveRun(hot_store, "run-b")
    sizes: list[int] = []

    async def follow() -> None:
        async for size in follow_sizes(run.recording()):
            sizes.append(size)

    async def scenario() -> None:
        follower = asyncio.create_task(follow())
        while run.hot.changes.waiting == 0:
            await asyncio.sleep(0)
        writer = threading.Thread(target=append, args=(run.hot,))
        writer.start()
        writer.join()
        while run.hot.changes.waiting == 0 or len(sizes) < 2:  # woken, then waiting again
            await asyncio.sleep(0.001)
        ender = threading.Thread(target=run.end)
        ender.start()
        ender.join()
        await asyncio.wait_for(follower, WAKE_S)

    asyncio.run(scenario())
    assert sizes == [sizes[0], run.hot.size] and sizes[1] > sizes[0]


def test_a_change_made_before_the_wait_is_not_missed():
    changes = Changes()

    async def scenario() -> None:
        seen = changes.count
        changes.notify()  # between looking at the run and waiting
        await asyncio.wait_for(changes.wait(seen), WAKE_S)
        await changes.wait(changes.count, timeout=0.01)  # nothing new: only the time limit ends it
        assert changes.waiting == 0

    asyncio.run(scenario())


def test_a_follower_that_goes_away_leaves_no_waiter(hot_store: HotStore):
    run = LiveRun(hot_store, "run-c")

    async def scenario() -> None:
        async def follow() -> None:
            async for _ in follow_sizes(run.recording()):
                pass

        follower = asyncio.create_task(follow())
        while run.hot.changes.waiting == 0:
            await asyncio.sleep(0)
        follower.cancel()  # the viewer disconnected
        with pytest.raises(asyncio.CancelledError):
            await follower
        assert run.hot.changes.waiting == 0
        append(run.hot)  # nobody to wake

    asyncio.run(scenario())
