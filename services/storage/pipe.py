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
        self._pieces: deque[bytes | bytearray | memoryview] = deque()
        self._held = 0
        self._closed = False
        self._failure: BaseException | None = None
        self._abandoned = False
        self._changed = threading.Condition()

    # --- the writer's side ----------------------------------------------------------------------

    def write(self, data: bytes | bytearray | memoryview) -> int:
        # Each byte is copied once on this side: gathered, or (a large write with nothing gathered)
        # copied as it comes, as what is written may be a view of a buffer its writer reuses.
        if not self._gathered and len(data) >= WRITE_PIECE:
            self._hand_over(bytes(data))
            return len(data)
        self._gathered += data
        if len(self._gathered) >= WRITE_PIECE:
            self._hand_over_gathered()
        return len(data)

    def _hand_over_gathered(self) -> None:
        piece, self._gathered = self._gathered, bytearray()  # handed over as it is, not copied
        self._hand_over(piece)

    def _hand_over(self, piece: bytes | bytearray) -> None:
        size = len(piece)
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
        self._hand_over_gathered()
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
        parts: list[bytes | bytearray | memoryview] = []
        taken = 0
        with self._changed:
            while n < 0 or taken < n:
                while not self._pieces and not self._closed and self._failure is None:
                    self._changed.wait()
                if self._failure is not None:
                    raise self._failure
                if not self._pieces:
                    break  # closed, and all read
                piece = self._pieces.popleft()
                wanted = len(piece) if n < 0 else min(len(piece), n - taken)
                if wanted < len(piece):  # the rest stays for the next read, as a view (not copied)
                    view = memoryview(piece)
                    piece = view[:wanted]
                    self._pieces.appendleft(view[wanted:])
                parts.append(piece)
                taken += wanted
                self._held -= wanted
                self._changed.notify_all()
        return b"".join(parts)  # the one copy on this side

    def abandon(self) -> None:
        """The reader gives up: the writer's next write raises `PipeAbandonedError`."""
        with self._changed:
            self._abandoned = True
            self._pieces.clear()
            self._held = 0
            self._changed.notify_all()
