"""Ranged reads of one object, several under way at once and handed on in order.

A download from the warm store reads its recording by ranges. Made one after another, each range
waits for the store's first byte again (on S3 and SeaweedFS tens of milliseconds), and a whole run
read in 1 MiB ranges came to a tenth of what one GET streams. `read_ahead` keeps up to `depth` reads
of what comes next under way while the caller sends what came first: a download holds at most
`depth` reads' bytes (the pieces it plans, at most `PIECE_BYTES` for a whole object), whatever the
size of the run.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections import deque
from collections.abc import Callable, Generator, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, TypeVar

PIECE_BYTES = 16 * 1024 * 1024  # a whole object is read in ranges of this size
DEPTH = 4  # reads under way at once for one download
ALONE_BYTES = 1024 * 1024  # a first read this large runs alone (`read_ahead`)
# Shared by every download of the process: a download's own reads never wait on each other (the
# caller waits for them, outside the pool), so a busy pool only queues them.
READ_THREADS = 32
_READS = ThreadPoolExecutor(max_workers=READ_THREADS, thread_name_prefix="store-read")

Plan = TypeVar("Plan")
Data = TypeVar("Data")


def read_ahead(
    plans: Iterable[Plan],
    read: Callable[[Plan], Data],
    depth: int = DEPTH,
    size: Callable[[Plan], int] | None = None,
) -> Generator[tuple[Plan, Data], None, None]:
    """Each of `plans` with what `read` gave for it, in the plans' order, with up to `depth` reads
    under way at once (1: one after another, on the caller's thread). A first read of at least
    `ALONE_BYTES` (by `size`) runs alone, the next ones start as it ends: the store's bandwidth goes
    to the bytes a client waits for first, not shared with reads it will need later (a smaller one
    waits mostly for the store's first byte, which it may as well wait for beside the next ones).
    Reads not yet handed on when the caller stops are cancelled (those under way finish and are
    dropped)."""
    if depth <= 1:
        for plan in plans:
            yield plan, read(plan)
        return
    pending: deque[tuple[Plan, Future[Data]]] = deque()
    starting = True  # the first plan
    try:
        for plan in plans:
            pending.append((plan, _READS.submit(read, plan)))
            if starting and size is not None and size(plan) >= ALONE_BYTES:
                wait([pending[0][1]])  # its error, if any, is raised where it is handed on
            starting = False
            if len(pending) >= depth:
                first, future = pending.popleft()
                yield first, future.result()
        while pending:
            first, future = pending.popleft()
            yield first, future.result()
    finally:
        for _, future in pending:
            future.cancel()


def read_soon(read: Callable[..., Data], *args: Any) -> Future[Data]:
    """`read(*args)` started now on the read threads: its result is asked for later."""
    return _READS.submit(read, *args)


_DONE = object()


def stream_ahead(source: Iterable[Data], depth: int = DEPTH) -> Generator[Data, None, None]:
    """`source`'s items in order, read on a thread of their own up to `depth` items ahead of the
    caller (a stream being sent while the next pieces arrive). An error of `source` is raised in
    its place; when the caller stops, the thread stops at its next item and `source` is closed."""
    ready: queue.Queue[Any] = queue.Queue(maxsize=depth)
    stopping = threading.Event()

    def offer(item: object) -> bool:
        """Put `item` when there is room; False once the caller has stopped."""
        while not stopping.is_set():
            try:
                ready.put(item, timeout=0.5)  # wakes now and then to see whether the caller stopped
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        items = iter(source)
        try:
            for item in items:
                if not offer(item):
                    return
            offer(_DONE)
        except BaseException as exc:  # handed to the caller, which raises it
            offer(_Failed(exc))
        finally:
            close = getattr(items, "close", None)
            if close is not None:
                close()

    producer = threading.Thread(target=produce, name="store-stream", daemon=True)
    producer.start()
    try:
        while (item := ready.get()) is not _DONE:
            if isinstance(item, _Failed):
                raise item.error
            yield item
    finally:
        stopping.set()
        with contextlib.suppress(queue.Empty):
            while True:  # frees the producer if it waits to put
                ready.get_nowait()


@dataclass(frozen=True)
class _Failed:
    error: BaseException


def pieces(start: int, end: int, first: int, piece: int = PIECE_BYTES) -> Iterator[tuple[int, int]]:
    """(offset, length) ranges covering [start, end): the first of `first` bytes (the first bytes
    go out soon), the others of `piece`."""
    offset, size = start, min(first, piece)
    while offset < end:
        length = min(size, end - offset)
        yield offset, length
        offset += length
        size = piece
