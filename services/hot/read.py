"""Reading a hot run's file: its messages as they stand, and, when following a live run, those
appended after, until the run closes.

Following waits on the run's `Changes` (woken by appends and by the run's end) on the event loop:
a follower holds no thread while the run is quiet, and only the reading itself may go to a worker
thread (the caller's choice, see services.runs.download.follow_run)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncGenerator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Protocol

from services.hot.direct import DirectFile
from services.hot.index import HotChunkIndex, HotEntry, iter_hot_index, read_hot_index
from services.hot.store import Changes
from services.rrd.decoder import RrdDecoder
from services.rrd.messages import Event

READ_BYTES = 1024 * 1024
# A follower reads at most this often: a busy run's many small appends are read (and sent) together,
# and a hundred followers of a run logging at a kHz wake 20 times a second each, not a thousand.
FOLLOW_BATCH_S = 0.05
# Besides its wake-ups, a follower looks at the run this often: a safety net that ends the stream
# even if the run's end came without a notification.
FOLLOW_RECHECK_S = 5.0
# A live run's file: () -> (bytes of whole messages now, whether the run is still live).
Follow = Callable[[], tuple[int, bool]]


@dataclass(frozen=True)
class HotRecording:
    """A run in this node's hot tier as a reader sees it: its file as it stands, its timelines, and
    how to follow it."""

    path: Path
    size: int  # bytes of whole messages when the reader asked
    timeline_types: dict[str, str]
    follow: Follow
    changes: Changes  # notified when the file grows or the run ends

    def chunk_index(self) -> HotChunkIndex:
        """Every message of the file up to `size` with its index row (and a chunk's metadata):
        from the chunk index kept beside the file, and what it lacks read from the file. Reads
        files only, so it may run on any thread while ingest appends."""
        return read_hot_index(self.path, self.size)

    def index_entries(self) -> Iterator[HotEntry]:
        """The entries of `chunk_index()`, one at a time as the index is read (a download that
        copies the run in file order starts before the whole index is parsed)."""
        return iter_hot_index(self.path, self.size)


class HotRuns(Protocol):
    """The hot runs of this node, read-only: what serving and analytics may ask of ingest."""

    def hot_recording(self, run_id: str) -> HotRecording | None: ...


class HotReader:
    """A run's file decoded from its start, a piece at a time, up to a size the caller gives (the
    bytes of whole messages it knows of). Not thread-safe: one step at a time, on any thread."""

    def __init__(self, path: Path, *, direct: bool = False) -> None:
        # `direct`: a whole run read once, around the page cache (services.hot.direct); a live run's
        # followers read its newest bytes, which the page cache keeps for them
        self._file: DirectFile | BinaryIO = (
            DirectFile(path, READ_BYTES) if direct else open(path, "rb")  # noqa: SIM115 - closed by close()
        )
        self._decoder = RrdDecoder()
        self.position = 0

    def read(self, size: int, limit: int = READ_BYTES) -> list[Event]:
        """The events of the next piece (at most `limit` bytes, not past `size`)."""
        piece = self._file.read(min(limit, size - self.position)) if self.position < size else b""
        if not piece:
            return []
        self.position += len(piece)
        return list(self._decoder.feed(piece))

    def finish(self) -> list[Event]:
        return list(self._decoder.finish())

    def close(self) -> None:
        self._file.close()


def read_events(path: Path, size: int) -> Iterator[Event]:
    """Events of the first `size` bytes of a run's file (following a live run: `follow_sizes`), read
    once around the page cache."""
    reader = HotReader(path, direct=True)
    try:
        while reader.position < size:
            before = reader.position
            yield from reader.read(size)
            if reader.position == before:
                break  # the file is shorter than `size`: what it holds was read
        yield from reader.finish()
    finally:
        reader.close()


async def follow_sizes(recording: HotRecording) -> AsyncGenerator[int, None]:
    """The bytes of whole messages in the run's file: `recording.size` first, then each time it has
    grown, until the run is no longer live. Waits on the run's changes, on the event loop."""
    size = recording.size
    yield size
    read_at = time.monotonic()
    while True:
        seen = recording.changes.count  # before looking: a change made after this ends the wait at once
        grown, live = recording.follow()
        if grown > size:
            pause = read_at + FOLLOW_BATCH_S - time.monotonic()
            if pause > 0:
                await asyncio.sleep(pause)  # let a busy run's appends gather into one read
                grown, live = recording.follow()
            size = grown
            read_at = time.monotonic()
            yield size
            continue
        if not live:
            return
        await recording.changes.wait(seen, FOLLOW_RECHECK_S)
