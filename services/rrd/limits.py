"""Memory limits of chunk decompression: how large a chunk may declare itself, and how many
decompressed bytes the process holds at once.

An LZ4 block may expand ~255x, so a small message can declare (and make us allocate) a huge
payload. `max_chunk_bytes` refuses such a declaration before anything is allocated (the decoder
checks it as each Arrow message is parsed). The budget bounds the sum over threads: readers of
stored runs (downloads, sealing) decompress every chunk for its metadata, and N concurrent readers
of big chunks would otherwise hold N chunks at once. Ingest runs on the asyncio event loop, which
must never wait: there the declared-size limit alone protects (and ingest handles one chunk at a
time per loop), so the budget is only taken in worker threads.

The limits are process-wide (like the memory they protect): `configure` sets them once at start
from the settings (FLEET_MAX_CHUNK_BYTES, FLEET_DECOMPRESS_BUDGET_BYTES).
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from contextlib import contextmanager

DEFAULT_MAX_CHUNK_BYTES = 256 * 1024 * 1024  # as large as the largest message (FLEET_MAX_MESSAGE_SIZE)
DEFAULT_DECOMPRESS_BUDGET_BYTES = 2 * DEFAULT_MAX_CHUNK_BYTES  # two of the largest chunks at once
# Chunks smaller than this are not counted: they are most chunks (the SDK flushes at ~1 MiB), and
# the few threads that read them at once hold little; counting them would cost every chunk.
UNCOUNTED_BYTES = 1024 * 1024


class ByteBudget:
    """A semaphore counted in bytes. A request larger than the whole budget waits for all of it
    (so a single chunk up to the chunk limit always gets through, alone)."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.available = total
        self.peak_held = 0  # most bytes held at once (for tests and measurements)
        self._cond = threading.Condition()

    def acquire(self, size: int) -> int:
        size = max(0, min(size, self.total))
        with self._cond:
            if self.available < size:
                self._cond.wait_for(lambda: self.available >= size)
            self.available -= size
            self.peak_held = max(self.peak_held, self.total - self.available)
        return size

    def release(self, size: int) -> None:
        with self._cond:
            self.available += size
            self._cond.notify_all()

    @contextmanager
    def hold(self, size: int) -> Iterator[None]:
        taken = self.acquire(size)
        try:
            yield
        finally:
            self.release(taken)


class ChunkLimits:
    def __init__(
        self, max_chunk_bytes: int = DEFAULT_MAX_CHUNK_BYTES, budget_bytes: int = DEFAULT_DECOMPRESS_BUDGET_BYTES
    ) -> None:
        self.max_chunk_bytes = max_chunk_bytes
        self.budget = ByteBudget(budget_bytes)


LIMITS = ChunkLimits()


def configure(max_chunk_bytes: int, budget_bytes: int) -> None:
    """Set the process's limits (once, at start, from the settings)."""
    global LIMITS
    LIMITS = ChunkLimits(max_chunk_bytes, budget_bytes)


def max_chunk_bytes() -> int:
    return LIMITS.max_chunk_bytes


def on_event_loop() -> bool:
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return False
    return True


def budget_for(size: int) -> ByteBudget | None:
    """The budget a chunk of `size` decompressed bytes must hold while it is read: None for small
    chunks and on the event loop (which never waits)."""
    if size < UNCOUNTED_BYTES or on_event_loop():
        return None
    return LIMITS.budget


@contextmanager
def holding(size: int) -> Iterator[None]:
    """Hold `size` decompressed bytes of the budget meanwhile, where `budget_for` says to."""
    budget = budget_for(size)
    if budget is None:
        yield
        return
    with budget.hold(size):
        yield
