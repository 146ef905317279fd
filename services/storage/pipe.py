"""A bounded pipe of bytes between two threads: one writes an object as it is made, the other uploads
it (`ObjectStore.put` reads a file to its end), so an object is never written out to a local file
first and never held whole in memory.

The writer blocks while `max_bytes` are waiting; the reader blocks until there are bytes, the end, or
a failure. A writer that fails calls `fail(exc)`: the reader raises it (the upload is abandoned, and
an S3 multipart upload aborted). A reader that gives up calls `abandon()`: the writer's next write
raises, so it stops making what nobody reads.
"""

from __future__ import annotations

import threading
from collections import deque


class PipeAbandonedError(RuntimeError):
    """The reader gave up: what is written goes nowhere."""


WRITE_PIECE = 1024 * 1024  # the writer's small writes are handed over in pieces of this size


class Pipe:
    def __init__(self, max_bytes: int = 16 * 1024 * 1024) -> None:
        self.max_bytes = max_bytes
        self._gathered = bytearray()  # the writer's, not yet handed over (one writer thread)
        self._pieces: deque[bytes] = deque()
        self._held = 0
        self._closed = False
        self._failure: BaseException | None = None
        self._abandoned = False
        self._changed = threading.Condition()

    # --- the writer's side ----------------------------------------------------------------------

    def write(self, data: bytes | bytearray | memoryview) -> int:
        self._gathered += data
        if len(self._gathered) >= WRITE_PIECE:
            self._hand_over()
        return len(data)

    def _hand_over(self) -> None:
        piece, size = bytes(self._gathered), len(self._gathered)
        self._gathered.clear()
        if not size:
            return
        with self._changed:
            while self._held and self._held + size > self.max_bytes and not self._abandoned:
                self._changed.wait()
            if self._abandoned:
                raise PipeAbandonedError("the reader of this pipe gave up")
            self._pieces.append(piece)
            self._held += size
            self._changed.notify_all()

    def close(self) -> None:
        """Nothing more comes: the reader reads what is left, then the end."""
        self._hand_over()
        with self._changed:
            self._closed = True
            self._changed.notify_all()

    def fail(self, exc: BaseException) -> None:
        """The writer failed: the reader raises `exc` instead of reading an end."""
        with self._changed:
            self._failure = exc
            self._changed.notify_all()

    # --- the reader's side ----------------------------------------------------------------------

    def readable(self) -> bool:
        return True

    def read(self, n: int = -1) -> bytes:
        """Up to `n` bytes (all that is left when `n` < 0), fewer only at the end."""
        out = bytearray()
        with self._changed:
            while n < 0 or len(out) < n:
                while not self._pieces and not self._closed and self._failure is None:
                    self._changed.wait()
                if self._failure is not None:
                    raise self._failure
                if not self._pieces:
                    break  # closed, and all read
                piece = self._pieces.popleft()
                wanted = len(piece) if n < 0 else min(len(piece), n - len(out))
                out += piece[:wanted]
                if wanted < len(piece):
                    self._pieces.appendleft(piece[wanted:])
                self._held -= wanted
                self._changed.notify_all()
        return bytes(out)

    def abandon(self) -> None:
        """The reader gives up: the writer's next write raises `PipeAbandonedError`."""
        with self._changed:
            self._abandoned = True
            self._pieces.clear()
            self._held = 0
            self._changed.notify_all()
