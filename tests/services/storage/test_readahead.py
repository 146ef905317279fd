"""Ranged reads under way at once, handed on in order, bounded, and cancelled when the reader stops."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest

from services.storage.readahead import ALONE_BYTES, pieces, read_ahead, stream_ahead
from tests.waiting import wait_for


class Reads:
    """A read that waits until `together` reads are under way (proving they overlap), and counts."""

    def __init__(self, together: int) -> None:
        self.together = threading.Barrier(together, timeout=10)
        self.lock = threading.Lock()
        self.started: list[int] = []
        self.running = self.most = 0

    def __call__(self, plan: int) -> str:
        with self.lock:
            self.started.append(plan)
            self.running += 1
            self.most = max(self.most, self.running)
        if plan < self.together.parties:  # the first reads meet: they were under way at once
            self.together.wait()
        with self.lock:
            self.running -= 1
        return f"data {plan}"


def test_reads_overlap_up_to_the_depth_and_come_back_in_order() -> None:
    reads = Reads(together=4)
    got = list(read_ahead(range(20), reads, depth=4))
    assert got == [(plan, f"data {plan}") for plan in range(20)]
    assert reads.most == 4  # never more than the depth at once (and the barrier saw four)


@pytest.mark.parametrize("first_size", [ALONE_BYTES, ALONE_BYTES - 1])
def test_a_large_first_read_runs_alone(first_size: int) -> None:
    # The bytes a client waits for first get the store's whole bandwidth: a large first read gives
    # the next one half a second to start beside it (which it did at once before), and none does;
    # a small one has the next ones beside it (what it waits for is the store's first byte).
    second_started = threading.Event()
    overlapped: list[bool] = []

    def read(plan: int) -> int:
        if plan == 0:
            overlapped.append(second_started.wait(0.5 if first_size >= ALONE_BYTES else 10))
        else:
            second_started.set()
        return plan

    sizes = [first_size] + [ALONE_BYTES] * 9
    assert [data for _, data in read_ahead(range(10), read, 4, sizes.__getitem__)] == list(range(10))
    assert overlapped == [first_size < ALONE_BYTES]


def test_depth_one_reads_on_the_callers_thread_one_after_another() -> None:
    threads: set[str] = set()

    def read(plan: int) -> int:
        threads.add(threading.current_thread().name)
        return plan * 2

    assert [data for _, data in read_ahead(range(5), read, depth=1)] == [0, 2, 4, 6, 8]
    assert threads == {threading.current_thread().name}


def test_a_reader_that_stops_early_leaves_the_rest_unread() -> None:
    reads = Reads(together=1)
    stream = read_ahead(range(1000), reads, depth=3)
    assert next(stream) == (0, "data 0")
    stream.close()
    assert len(reads.started) <= 3  # what was asked ahead, not the other 997


def test_a_failed_read_is_raised_where_its_data_would_be() -> None:
    def read(plan: int) -> int:
        if plan == 2:
            raise OSError("store down")
        return plan

    stream = read_ahead(range(5), read, depth=3)
    assert [next(stream), next(stream)] == [(0, 0), (1, 1)]
    with pytest.raises(OSError, match="store down"):
        next(stream)


def test_pieces_cover_the_range_with_a_small_first_one() -> None:
    assert list(pieces(0, 25, first=3, piece=10)) == [(0, 3), (3, 10), (13, 10), (23, 2)]
    assert list(pieces(5, 7, first=3, piece=10)) == [(5, 2)]
    assert list(pieces(0, 0, first=3, piece=10)) == []


# --- a stream read ahead on a thread of its own ---------------------------------------------------


class Source:
    """A stream of numbered pieces that records how far it was read and whether it was closed."""

    def __init__(self, count: int, fail_at: int | None = None) -> None:
        self.count, self.fail_at = count, fail_at
        self.made = 0
        self.closed = threading.Event()

    def __iter__(self) -> Iterator[int]:
        try:
            for n in range(self.count):
                if n == self.fail_at:
                    raise OSError("the store broke off")
                self.made = n + 1
                yield n
        finally:
            self.closed.set()


def test_a_stream_comes_in_order_read_no_further_ahead_than_the_depth() -> None:
    source = Source(50)
    stream = stream_ahead(source, depth=3)
    assert next(stream) == 0
    # the producer fills the queue and stops: at most depth pieces waiting, one in its hand
    wait_for(lambda: source.made >= 4, 10, "the producer to read ahead")
    assert source.made <= 1 + 3 + 1
    assert [0, *stream] == list(range(50))
    assert source.closed.is_set()


def test_a_stream_error_is_raised_where_its_piece_would_be() -> None:
    stream = stream_ahead(Source(10, fail_at=4), depth=2)
    assert [next(stream) for _ in range(4)] == [0, 1, 2, 3]
    with pytest.raises(OSError, match="broke off"):
        next(stream)


def test_a_reader_that_stops_early_stops_the_stream_and_closes_it() -> None:
    source = Source(10_000)
    stream = stream_ahead(source, depth=2)
    assert next(stream) == 0
    stream.close()
    assert source.closed.wait(10), "the source was left open"
    assert source.made < 10  # stopped near where the reader stopped, not read to its end
