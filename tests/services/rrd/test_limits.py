"""The process's decompression budget (services/rrd/limits.py): readers in worker threads wait for
it, the event loop never does."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator

import pytest

from services.rrd import limits
from services.rrd.chunk import chunk_meta, decompressed_size
from services.rrd.messages import ArrowMessage
from tests.services.rrd.test_bad_input import arrow_body, chunk_ipc, one_arrow


@pytest.fixture
def message() -> ArrowMessage:
    return one_arrow(arrow_body(chunk_ipc(frames=tuple(range(200)), scalars=tuple([1.0] for _ in range(200)))))


@pytest.fixture
def small_budget(message: ArrowMessage, monkeypatch: pytest.MonkeyPatch) -> Iterator[limits.ByteBudget]:
    """A budget of one and a half chunks (restored afterwards), which counts even small chunks."""
    monkeypatch.setattr(limits, "UNCOUNTED_BYTES", 0)
    before = limits.LIMITS
    limits.configure(before.max_chunk_bytes, decompressed_size(message) * 3 // 2)
    yield limits.LIMITS.budget
    limits.LIMITS = before


def test_small_chunks_are_not_counted(message: ArrowMessage) -> None:
    assert limits.budget_for(decompressed_size(message)) is None
    assert limits.budget_for(limits.UNCOUNTED_BYTES) is limits.LIMITS.budget


def test_a_request_larger_than_the_budget_waits_for_all_of_it() -> None:
    budget = limits.ByteBudget(100)
    assert budget.acquire(1000) == 100 and budget.available == 0
    budget.release(100)
    with budget.hold(40):
        assert budget.available == 60
    assert budget.available == 100 and budget.peak_held == 100


def test_a_worker_thread_waits_for_the_budget(message: ArrowMessage, small_budget: limits.ByteBudget) -> None:
    taken = small_budget.acquire(small_budget.total)  # another reader holds everything
    done = threading.Event()

    def read() -> None:
        chunk_meta(message)
        done.set()

    worker = threading.Thread(target=read)
    worker.start()
    assert not done.wait(0.5), "chunk_meta decompressed without its share of the budget"
    small_budget.release(taken)
    worker.join(timeout=30)
    assert done.is_set()


def test_the_event_loop_never_waits(message: ArrowMessage, small_budget: limits.ByteBudget) -> None:
    """Ingest runs on the event loop: it is protected by the declared-size limit, not the budget."""
    small_budget.acquire(small_budget.total)

    async def index() -> int:
        return chunk_meta(message).num_rows

    assert asyncio.run(index()) == 200


def test_concurrent_readers_hold_at_most_the_budget(message: ArrowMessage, small_budget: limits.ByteBudget) -> None:
    errors: list[BaseException] = []

    def read() -> None:
        try:
            for _ in range(50):
                chunk_meta(message)
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=read) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors
    assert small_budget.available == small_budget.total
    assert decompressed_size(message) <= small_budget.peak_held <= small_budget.total
