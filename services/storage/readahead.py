"""Ranged reads of one object, several under way at once and handed on in order.

A download from the warm store reads its recording by ranges. Made one after another, each range
waits for the store's first byte again (on S3 and SeaweedFS tens of milliseconds), and a whole run
read in 1 MiB ranges came to a tenth of what one GET streams. `read_ahead` keeps up to `depth` reads
of what comes next under way while the caller sends what came first: a download holds at most
`depth` reads' bytes (the pieces it plans, at most `PIECE_BYTES` for a whole object), whatever the
size of the run.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Generator, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

PIECE_BYTES = 16 * 1024 * 1024  # a whole object is read in ranges of this size
DEPTH = 4  # reads under way at once for one download
# Shared by every download of the process: a download's own reads never wait on each other (the
# caller waits for them, outside the pool), so a busy pool only queues them.
READ_THREADS = 32
_READS = ThreadPoolExecutor(max_workers=READ_THREADS, thread_name_prefix="store-read")

Plan = TypeVar("Plan")
Data = TypeVar("Data")


def read_ahead(
    plans: Iterable[Plan], read: Callable[[Plan], Data], depth: int = DEPTH
) -> Generator[tuple[Plan, Data], None, None]:
    """Each of `plans` with what `read` gave for it, in the plans' order, with up to `depth` reads
    under way at once (1: one after another, on the caller's thread). Reads not yet handed on when
    the caller stops are cancelled (those under way finish and are dropped)."""
    if depth <= 1:
        for plan in plans:
            yield plan, read(plan)
        return
    pending: deque[tuple[Plan, Future[Data]]] = deque()
    try:
        for plan in plans:
            pending.append((plan, _READS.submit(read, plan)))
            if len(pending) >= depth:
                first, future = pending.popleft()
                yield first, future.result()
        while pending:
            first, future = pending.popleft()
            yield first, future.result()
    finally:
        for _, future in pending:
            future.cancel()


def pieces(start: int, end: int, first: int, piece: int = PIECE_BYTES) -> Iterator[tuple[int, int]]:
    """(offset, length) ranges covering [start, end): the first of `first` bytes (the first bytes
    go out soon), the others of `piece`."""
    offset, size = start, min(first, piece)
    while offset < end:
        length = min(size, end - offset)
        yield offset, length
        offset += length
        size = piece
