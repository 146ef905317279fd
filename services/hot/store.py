"""The hot tier: one append-only RRD file per run on the ingest node's disk.

`hot/<run>/run.rrd` is a stream header followed by whole messages (no End: the run is still
open), so it is a valid footer-less RRD at every moment a write completed. A message is written
with one `writev`; if that fails part-way the file is cut back, so there is never a half-written
chunk. After a crash, `recover()` trims a torn tail and rebuilds the run from what is on disk.
Durability: `always` fsyncs when a caller asks (an upload before it is answered, a stream at its
end), `interval` fsyncs dirty runs every `interval_ms` from a group-commit thread, `off` never.
Readers following a run wait on its `changes` (a wake-up per append and when the run ends), not on
a timer. Beside the file, `chunks.idx` indexes every message as it is appended (`hot.index`), so a
reader learns what a run holds without decompressing its chunks.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import shutil
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

from core.errors import InsufficientStorageError
from services.hot.index import HotIndexWriter
from services.rrd import errors as rrd_errors
from services.rrd.chunk import ChunkMeta
from services.rrd.decoder import iter_events
from services.rrd.frames import MESSAGE_HEADER_SIZE, RerunVersion, StreamHeader, encode_message_header
from services.rrd.messages import Buffer, Event, StoreKind, StreamStart
from services.settings import Durability

log = logging.getLogger(__name__)

RUN_FILE = "run.rrd"
ROBOT_FILE = "robot"  # the robot of a run whose token named it (a robot's ingest token)
_RECHECK_BYTES = 8 * 1024 * 1024
# What the page cache keeps of a run file once its bytes are on disk: its last CACHED_TAIL bytes, where
# followers read. The rest is dropped after each sync (POSIX_FADV_DONTNEED): promotion reads the file
# once, so caching it all only takes memory (a container's page cache counts against its memory
# limit), and the pages dropped are the ones the kernel hands out for the next writes, which costs
# less than taking new ones (writes into the page cache measured 1.5 -> 2.4 GB/s here).
CACHED_TAIL = 8 * 1024 * 1024


class Changes:
    """Wakes the readers following a run when its file grows or the run ends.

    `notify` may be called from any thread (appends happen on the event loop, promotion and tests
    may close runs from others); each waiter is woken on its own loop. A reader takes `count`
    before it looks at the run and passes it to `wait`, so a change made in between is never
    missed. Costs an append a lock and a counter when nobody follows."""

    def __init__(self) -> None:
        self.count = 0
        self._lock = threading.Lock()
        self._waiters: set[tuple[asyncio.AbstractEventLoop, asyncio.Future[None]]] = set()

    @property
    def waiting(self) -> int:
        """Readers waiting now."""
        return len(self._waiters)

    def notify(self) -> None:
        with self._lock:
            self.count += 1
            waiters, self._waiters = self._waiters, set()
        if not waiters:
            return
        try:
            here: asyncio.AbstractEventLoop | None = asyncio.get_running_loop()
        except RuntimeError:
            here = None
        by_loop: dict[asyncio.AbstractEventLoop, list[asyncio.Future[None]]] = {}
        for loop, future in waiters:
            by_loop.setdefault(loop, []).append(future)
        for loop, futures in by_loop.items():
            if loop is here:
                _wake(futures)
            else:  # one wake-up of the other loop for all its waiters
                with contextlib.suppress(RuntimeError):  # that loop is closed: nobody waits there any more
                    loop.call_soon_threadsafe(_wake, futures)

    async def wait(self, seen: int, timeout: float | None = None) -> None:
        """Return once `count` differs from `seen` (at once if it already does), or after `timeout`."""
        loop = asyncio.get_running_loop()
        future: asyncio.Future[None] = loop.create_future()
        waiter = (loop, future)
        with self._lock:
            if self.count != seen:
                return
            self._waiters.add(waiter)
        try:
            await asyncio.wait_for(future, timeout)
        except TimeoutError:
            pass
        finally:
            with self._lock:
                self._waiters.discard(waiter)


def _wake(futures: list[asyncio.Future[None]]) -> None:
    for future in futures:
        if not future.done():
            future.set_result(None)


class HotRun:
    """The append-only file of one run."""

    def __init__(
        self, directory: Path, fd: int, size: int, robot: str | None = None, index: HotIndexWriter | None = None
    ) -> None:
        self.directory = directory
        self.run_id = directory.name
        self.robot = robot  # the robot whose token created the run, if one did (kept in ROBOT_FILE)
        self._fd = fd
        self.size = size
        self.index = index  # the chunk index beside the file (None: not kept)
        self.dirty = False
        self.closed = False
        self.uncached = 0  # the page cache was told to drop the bytes before this offset
        # Syncs run on worker threads (durability=always, group commit) while the loop appends: a
        # caller returns only once the bytes it wrote are on disk, even if another sync cleared
        # `dirty` first, and the file is never closed under a sync.
        self._sync_lock = threading.Lock()
        self.changes = Changes()  # followers wait on it: the file grew, or the run ended

    @property
    def path(self) -> Path:
        return self.directory / RUN_FILE

    @classmethod
    def create(cls, directory: Path, version: RerunVersion, robot: str | None = None) -> HotRun:
        directory.mkdir(parents=True, exist_ok=False)
        if robot is not None:  # before the run file: a run recovered after a crash knows its robot
            _write_synced(directory / ROBOT_FILE, robot.encode())
        header = StreamHeader(version).encode()
        fd = os.open(directory / RUN_FILE, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o644)
        os.write(fd, header)
        os.fsync(fd)
        _fsync_dir(directory.parent)  # the new run survives a crash even with durability off
        return cls(directory, fd, len(header), robot, HotIndexWriter.create(directory, len(header)))

    @classmethod
    def recover(cls, directory: Path) -> HotRun:
        """Reopen a run after a restart: every whole message is kept, a torn tail is cut off, and
        the chunk index made to match what is kept. The file is read once as it streams by, so a
        run of any size recovers in the memory of a few messages."""
        path = directory / RUN_FILE
        messages = _WholeMessages(path)
        index = HotIndexWriter.recover(directory, messages)
        size = path.stat().st_size
        if messages.good < size:
            log.warning(
                "hot run %s: cut a torn tail of %d bytes at byte %d",
                directory.name,
                size - messages.good,
                messages.good,
            )
            os.truncate(path, messages.good)
        fd = os.open(path, os.O_WRONLY | os.O_APPEND)
        robot_file = directory / ROBOT_FILE
        robot = robot_file.read_text().strip() or None if robot_file.is_file() else None
        return cls(directory, fd, messages.good, robot, index)

    def append(
        self, kind: int, raw: Buffer, store_kind: StoreKind = StoreKind.RECORDING, meta: ChunkMeta | None = None
    ) -> int:
        """Write one whole message; returns the offset of its header. `store_kind` and, for a
        chunk, `meta` are what the chunk index records of it (a chunk without: the index stops
        there and readers read on from the file)."""
        offset = self.size
        header = encode_message_header(kind, len(raw))
        try:
            written = os.writev(self._fd, [header, raw])
            if written != MESSAGE_HEADER_SIZE + len(raw):
                raise OSError(f"short write: {written} of {MESSAGE_HEADER_SIZE + len(raw)} bytes")
        except OSError as exc:
            os.ftruncate(self._fd, offset)  # never leave half a message behind
            raise InsufficientStorageError(f"cannot write run {self.run_id} to the hot tier: {exc}") from exc
        self.size = offset + written
        self.dirty = True
        if self.index is not None:
            self.index.add(kind, store_kind, offset, written, meta)
        self.changes.notify()
        return offset

    def sync(self) -> None:
        with self._sync_lock:
            if self.dirty and not self.closed:
                self.dirty = False
                synced = self.size  # read before the fsync: every byte below it is on disk after it
                os.fsync(self._fd)
                self._uncache(synced - CACHED_TAIL)

    def _uncache(self, end: int) -> None:
        """Drop the run file's cached pages below `end` (on disk already), a CACHED_TAIL at a time."""
        if end - self.uncached < CACHED_TAIL:
            return
        try:
            os.posix_fadvise(self._fd, self.uncached, end - self.uncached, os.POSIX_FADV_DONTNEED)
        except OSError:  # closed meanwhile, or a file system that cannot: the pages stay cached
            return
        self.uncached = end

    def close(self) -> None:
        if not self.closed:
            self.sync()
            with self._sync_lock:
                self.closed = True
                os.close(self._fd)
            if self.index is not None:
                self.index.close()
            self.changes.notify()


def _end_of(event: Event) -> int:
    if isinstance(event, StreamStart):
        return event.offset + len(event.header.encode())
    return event.offset + MESSAGE_HEADER_SIZE + len(getattr(event, "raw", b""))


def _write_synced(path: Path, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class HotStore:
    """All hot runs under `root`, the disk guard and the group commit."""

    def __init__(self, root: Path, *, durability: Durability, interval_ms: int, min_free_bytes: int) -> None:
        self.root = root
        self.durability = durability
        self.interval_ms = interval_ms
        self.min_free_bytes = min_free_bytes
        self.runs: dict[str, HotRun] = {}
        self._free: int | None = None
        self._since_check = 0
        self._checked_at = 0.0
        self._stop = threading.Event()
        self._committer: threading.Thread | None = None
        root.mkdir(parents=True, exist_ok=True)

    def existing(self) -> Iterator[Path]:
        for directory in sorted(self.root.iterdir()):
            if not directory.name.startswith(".") and (directory / RUN_FILE).is_file():
                yield directory

    def set_aside(self, run: HotRun) -> Path:
        """Move a forgotten run's folder out of the way (a new hot run of the same id may start at
        once); returns where it went, for the caller to remove."""
        aside = self.root / f".{run.run_id}.{uuid.uuid4().hex[:8]}.done"
        os.rename(run.directory, aside)
        return aside

    def sweep(self) -> None:
        """Remove folders set aside by a process that stopped before removing them."""
        for directory in self.root.iterdir():
            if directory.name.startswith(".") and directory.name.endswith(".done"):
                shutil.rmtree(directory, ignore_errors=True)

    def create(self, run_id: str, version: RerunVersion, robot: str | None = None) -> HotRun:
        run = HotRun.create(self.root / run_id, version, robot)
        self.runs[run_id] = run
        return run

    def recover(self, directory: Path) -> HotRun:
        run = HotRun.recover(directory)
        self.runs[run.run_id] = run
        return run

    def check_space(self, incoming: int) -> None:
        """Refuse new data before the disk fills (INSUFFICIENT_STORAGE: HTTP 507, gRPC RESOURCE_EXHAUSTED).

        The free space is asked of the file system at most every 8 MiB written or 100 ms; in
        between it is counted down, so the guard costs no system call per chunk."""
        now = time.monotonic()
        if self._free is None or self._since_check + incoming > _RECHECK_BYTES or now - self._checked_at > 0.1:
            self._free = shutil.disk_usage(self.root).free
            self._since_check, self._checked_at = 0, now
        free = self._free - self._since_check
        self._since_check += incoming
        if free - incoming < self.min_free_bytes:
            self._free = None  # ask again next time: space may have been freed
            raise InsufficientStorageError(
                f"hot tier {self.root} has {free} bytes free, the guard keeps {self.min_free_bytes}: "
                "new data is refused until runs are promoted or space is freed (FLEET_MIN_FREE_BYTES)"
            )

    def forget(self, run: HotRun) -> None:
        """The run left the hot tier: stop syncing it and close its file (the caller removes it)."""
        self.runs.pop(run.run_id, None)
        run.close()

    def discard(self, run: HotRun) -> None:
        """Forget a run and remove its files."""
        self.forget(run)
        shutil.rmtree(run.directory, ignore_errors=True)
        _fsync_dir(self.root)

    def sync(self, runs: list[HotRun] | None = None) -> None:
        for run in runs if runs is not None else list(self.runs.values()):
            if not run.closed:
                run.sync()

    def sync_if_always(self, runs: list[HotRun]) -> None:
        if self.durability is Durability.ALWAYS:
            self.sync(runs)

    def start(self) -> None:
        if self.durability is Durability.INTERVAL and self._committer is None:
            self._committer = threading.Thread(target=self._group_commit, name="hot-group-commit", daemon=True)
            self._committer.start()

    def _group_commit(self) -> None:
        while not self._stop.wait(self.interval_ms / 1000):
            try:
                self.sync()
            except OSError:
                log.exception("group commit failed")

    def close(self) -> None:
        self._stop.set()
        if self._committer is not None:
            self._committer.join(timeout=5)
        for run in self.runs.values():
            run.close()
        self.runs.clear()


class _WholeMessages:
    """The events of a run file up to its first torn or damaged message; `good` is where the last
    whole one ends once they have been read."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.good = 0

    def __iter__(self) -> Iterator[Event]:
        try:
            for event in iter_events(self.path):
                self.good = _end_of(event)  # decoded: whole
                yield event
        except rrd_errors.TruncatedError:
            pass  # a crash cut the last message: everything before it is kept
        except rrd_errors.RrdError as exc:
            log.error(
                "hot run %s is damaged at byte %d (%s): keeping what precedes it",
                self.path.parent.name,
                exc.offset,
                exc,
            )
