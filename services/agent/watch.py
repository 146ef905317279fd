"""Watching the folders where robots write .rrd files (FileSink), and handing what `FileTail` reads
from each to the agent: notified by the file system (`watchfiles`), and rescanned every
`rescan_s` where it does not notify; file reads and decoding on worker threads, in bounded batches.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import threading
import time
from collections.abc import Awaitable, Callable, Iterable, Sequence
from pathlib import Path
from typing import Any, cast

import watchfiles

from services.agent.files import BATCH_BYTES, DEFAULT_IDLE_S, DEFAULT_RESCAN_S, FileProgress, FileTail
from services.rrd.decoder import DEFAULT_MAX_MESSAGE_SIZE
from services.rrd.messages import Event

log = logging.getLogger("services.agent.files")


def is_recording_name(name: str) -> bool:
    """A file name the watcher imports: `*.rrd`, not hidden, not an editor's or copier's temp file."""
    return name.endswith(".rrd") and not name.startswith((".", "~", "#")) and len(name) > len(".rrd")


OnEvents = Callable[[Path, list[Event], FileProgress], Awaitable[None]]
OnComplete = Callable[[Path, FileProgress], Awaitable[None]]


class FileWatcher:
    """Imports every .rrd file under `directories` (hidden files and directories left out) as it grows.

    For each file with new whole messages it awaits `on_events(path, events, progress)`, about
    `batch_bytes` of messages at a time: store `progress` once the events are filed. If the callback
    raises, the same events are read again later. `on_complete(path, progress)` is awaited when a
    file becomes complete (again, if it grew after). `progress` is what the agent stored, so a
    restart resumes where it was. Files are read and decoded in worker threads, callbacks run on
    the event loop. A watched directory that does not exist is looked for at every rescan."""

    def __init__(
        self,
        directories: Sequence[str | os.PathLike[str]],
        on_events: OnEvents,
        on_complete: OnComplete | None = None,
        *,
        progress: Iterable[FileProgress] = (),
        rescan_s: float = DEFAULT_RESCAN_S,
        idle_s: float = DEFAULT_IDLE_S,
        batch_bytes: int = BATCH_BYTES,
        notify: bool = True,
        max_message_size: int = DEFAULT_MAX_MESSAGE_SIZE,
    ) -> None:
        self.directories = [Path(d).absolute() for d in directories]
        self.on_events, self.on_complete = on_events, on_complete
        self.rescan_s, self.idle_s, self.batch_bytes = rescan_s, idle_s, batch_bytes
        self.notify = notify  # False: the rescan alone finds new data
        self.max_message_size = max_message_size
        self._known = {p.path: p for p in progress}
        self._tails: dict[str, FileTail] = {}
        self._failing: set[str] = set()  # read or filing failed: tried again at the next rescan
        self._missing: set[Path] = set()
        self._changed: set[str] = set()
        self._full_scan = True
        self._wake = asyncio.Event()
        self._roots: tuple[str, ...] = ()
        self._task: asyncio.Task[None] | None = None
        self.scanned = asyncio.Event()  # set once `run` has watched and scanned every directory

    def progress(self) -> dict[str, FileProgress]:
        """Where each file known to the watcher stands, by path."""
        known = {path: dataclasses.replace(p) for path, p in self._known.items()}
        return known | {path: tail.progress for path, tail in self._tails.items()}

    def start(self) -> asyncio.Task[None]:
        self._task = asyncio.create_task(self.run(), name="file-watcher")
        return self._task

    async def stop(self) -> None:
        """Cancel `run` (started by `start`) and wait until it has stopped."""
        await _finish(self._task)
        self._task = None

    async def run(self) -> None:
        """Watch and import until cancelled."""
        stop_watch = threading.Event()
        watching: asyncio.Task[None] | None = None
        next_scan = 0.0
        try:
            while True:
                self._wake.clear()
                changed, self._changed = self._changed, set()
                if self._full_scan or time.monotonic() >= next_scan:
                    self._full_scan = False
                    roots = await asyncio.to_thread(self._existing_roots)
                    if self.notify and roots != self._roots:
                        # Watch first, then list: a file made in between is seen by one or the other.
                        stop_watch.set()
                        await _finish(watching)
                        stop_watch, self._roots = threading.Event(), roots
                        watching = asyncio.create_task(self._watch(roots, stop_watch)) if roots else None
                        await asyncio.sleep(0)
                    await self._scan(roots)
                    next_scan = time.monotonic() + self.rescan_s
                    self.scanned.set()
                else:
                    now = time.monotonic()
                    await self.import_files(changed | {p for p, at in self._idle_deadlines().items() if at <= now})
                wait = min([next_scan, *self._idle_deadlines().values()]) - time.monotonic()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), max(wait, 0.0))
        finally:
            stop_watch.set()  # the notify thread returns at once, so cancelling does not wait for it
            await _finish(watching)
            self._roots = ()

    async def scan(self) -> None:
        """One full pass: find every file under the directories and import what each has new
        (for a watcher that is not running: `run` does this every `rescan_s`)."""
        await self._scan(await asyncio.to_thread(self._existing_roots))

    async def _scan(self, roots: tuple[str, ...]) -> None:
        found = await asyncio.to_thread(_find_recordings, roots)
        await self.import_files(found | set(self._tails))

    async def import_files(self, paths: Iterable[str]) -> None:
        """Import what each file has new, a batch of each in turn until none has more."""
        pending = sorted(paths)
        while pending:
            pending = [path for path in pending if await self._import_batch(path)]

    async def _import_batch(self, path: str) -> bool:
        """Read and hand over one batch of `path`; True if it has more to read now."""
        tail = self._tails.get(path) or self._new_tail(path, self._known.pop(path, None))
        self._tails[path] = tail
        before = tail.progress
        try:
            batch = await asyncio.to_thread(tail.read, self.batch_bytes)
        except FileNotFoundError:
            self._tails.pop(path, None)
            self._failing.discard(path)
            return False
        except OSError as exc:
            self._failed(path, f"{path}: cannot be read ({exc}); trying again every {self.rescan_s} s")
            return False
        except BaseException:
            self._tails[path] = self._new_tail(path, before)  # a cancelled read is read again
            raise
        try:
            if batch.events:
                await self.on_events(Path(path), batch.events, batch.progress)
        except Exception as exc:
            self._tails[path] = self._new_tail(path, before)
            self._failed(path, f"{path}: filing {len(batch.events)} messages failed ({exc!r}); they are read again")
            return False
        except BaseException:
            self._tails[path] = self._new_tail(path, before)
            raise
        self._failing.discard(path)
        if batch.completed and self.on_complete is not None:
            try:
                await self.on_complete(Path(path), batch.progress)
            except Exception as exc:
                self._tails[path] = self._new_tail(path, dataclasses.replace(batch.progress, complete=False))
                self._failed(path, f"{path}: handling its completion failed ({exc!r}); tried again")
        return batch.more

    def _failed(self, path: str, problem: str) -> None:
        if path not in self._failing:  # one warning per failure, not one per retry
            log.warning("%s", problem)
        self._failing.add(path)

    def _new_tail(self, path: str, progress: FileProgress | None) -> FileTail:
        return FileTail(path, progress, idle_s=self.idle_s, max_message_size=self.max_message_size)

    def _idle_deadlines(self) -> dict[str, float]:
        """When each file not yet complete becomes complete if it does not grow (not those failing)."""
        deadlines = {path: tail.idle_deadline() for path, tail in self._tails.items() if path not in self._failing}
        return {path: deadline for path, deadline in deadlines.items() if deadline is not None}

    def _existing_roots(self) -> tuple[str, ...]:
        """The watched directories that exist (resolved); one warning for each that does not."""
        roots: list[str] = []
        for directory in self.directories:
            if not directory.is_dir():
                if directory not in self._missing:
                    self._missing.add(directory)
                    log.warning(
                        "watched directory %s does not exist (or is not a directory): looking again every %s s",
                        directory,
                        self.rescan_s,
                    )
                continue
            if directory in self._missing:
                self._missing.discard(directory)
                log.info("watched directory %s exists now", directory)
            roots.append(os.path.realpath(directory))
        return tuple(roots)

    async def _watch(self, roots: tuple[str, ...], stop: threading.Event) -> None:
        """Wake the import loop when the file system reports a change under `roots`."""
        try:
            # A threading.Event (set from the agent's other threads): awatch only polls is_set(),
            # which it has, though its signature names the async libraries' events.
            stop_event = cast(Any, stop)
            async for changes in watchfiles.awatch(*roots, watch_filter=None, stop_event=stop_event, step=50):
                for change, path in changes:
                    if self._wanted(path, roots):
                        self._changed.add(path)
                    elif change == watchfiles.Change.added and os.path.isdir(path):
                        self._full_scan = True  # files made in it before it was watched are found by the scan
                self._wake.set()
        except Exception as exc:  # e.g. the OS's limit of watches: the rescan still finds everything
            log.warning("watching %s for changes failed (%s): new data is found every %s s", roots, exc, self.rescan_s)

    @staticmethod
    def _wanted(path: str, roots: tuple[str, ...]) -> bool:
        if not is_recording_name(os.path.basename(path)):
            return False
        for root in roots:
            if path.startswith(root + os.sep):
                return not any(part.startswith(".") for part in Path(path[len(root) + 1 :]).parts)
        return False


def _find_recordings(roots: Iterable[str]) -> set[str]:
    found: set[str] = set()
    for root in roots:
        for parent, dirs, files in os.walk(root):
            dirs[:] = [d for d in dirs if not d.startswith(".")]  # hidden directories are skipped
            found.update(os.path.join(parent, name) for name in files if is_recording_name(name))
    return found


async def _finish(task: asyncio.Task[None] | None) -> None:
    if task is not None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
