"""A run's file read once, front to back, around the page cache (O_DIRECT).

Why: a run's pages are dropped from the page cache once they are on disk (services.hot.store), so
the readers of a whole run (sealing, hand-over, scrub) read the disk. Through the page cache, each
GB read that way cost the kernel 0.2-3 s of CPU on the machine the benchmarks run on (pages taken
for the cache, filled, then copied out), as much as all the rest of a promotion's share of the
depot's CPU; read straight into one reused buffer, 0.06-0.15 s, at 800 MB/s from one read at a time.
Nothing is left in the cache either, for a 50 GB run to push other files out with.

Direct reads start and end on the device's blocks (ALIGN), so a read that starts or stops between
blocks reads the blocks around it and hands out only what was asked. Where the file system refuses
direct reads (tmpfs, some network file systems) the file is read through the page cache, as before.
"""

from __future__ import annotations

import errno
import mmap
import os
from pathlib import Path

ALIGN = 4096  # a multiple of every common logical block size (512 B, 4 KiB)


def _round_up(n: int, to: int) -> int:
    return -(-n // to) * to


class DirectFile:
    """A file read by position, each read at most `max_read` bytes (fewer at its end)."""

    def __init__(self, path: Path, max_read: int) -> None:
        self.path = path
        self.position = 0
        self.direct = hasattr(os, "O_DIRECT")
        self._fd = self._open()
        self._buffer = mmap.mmap(-1, _round_up(max_read, ALIGN) + ALIGN)  # page-aligned, as direct reads need
        self._view = memoryview(self._buffer)

    def _open(self) -> int:
        if self.direct:
            try:
                return os.open(self.path, os.O_RDONLY | os.O_CLOEXEC | os.O_DIRECT)
            except OSError as exc:
                if exc.errno != errno.EINVAL:
                    raise
                self.direct = False  # the file system has no direct reads
        return os.open(self.path, os.O_RDONLY | os.O_CLOEXEC)

    def read(self, n: int) -> bytes:
        """Up to `n` bytes from the current position (fewer at the end of the file, none after it)."""
        if not self.direct:
            data = os.pread(self._fd, min(n, len(self._buffer)), self.position)
        else:
            start = self.position - self.position % ALIGN
            skip = self.position - start
            length = min(_round_up(skip + n, ALIGN), len(self._buffer))
            try:
                got = os.preadv(self._fd, [self._view[:length]], start)
            except OSError as exc:
                if exc.errno != errno.EINVAL:
                    raise
                self._fall_back()  # the device wants larger blocks than ALIGN: read it as any file
                return self.read(n)
            data = self._buffer[skip : max(skip, min(got, skip + n))]
        self.position += len(data)
        return data

    def _fall_back(self) -> None:
        os.close(self._fd)
        self.direct = False
        self._fd = self._open()

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
            self._view.release()
            self._buffer.close()
