"""The SQL worker pool: every query in a worker process of its own, with limits held from outside.

At most `Limits.workers` queries run at once, each in its own thread of a private executor (never
the threadpool FastAPI's sync handlers share) driving a worker process; up to `Limits.queue` more
wait; beyond that a query is refused at once (429). The time limit counts from a query's arrival,
its wait in the queue included: one still waiting when its limit falls is refused (429 with
Retry-After) rather than run late, so no answer comes later than the limit. Idle workers are
started ahead (interpreter and DuckDB imported), one per running slot, and told which files the
last query's tables have now, to read their footers while they wait (warming.py). While a worker
runs, its thread watches the clock and the worker's resident memory and kills it past either limit:
DuckDB's interrupt does not reach parsing or planning, and its memory_limit does not cover every
allocation.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import json
import logging
import math
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa

import services
from core.errors import (
    ErrorCode,
    FleetError,
    InternalError,
    InvalidSqlError,
    QueryOutOfMemoryError,
    QueryTimeoutError,
    ResultTooLargeError,
    SqlNotAllowedError,
)
from services.analytics import worker
from services.analytics.sql import ANALYTICS_VIEWS, Limits, SqlBusyError, out_of_memory
from services.rrd import untrusted
from services.rrd.errors import RrdError
from services.storage.objectstore import StorageError

log = logging.getLogger(__name__)
POLL_S = 0.02  # how often a running worker's clock and memory are checked
START_S = 60.0  # a worker not ready (imports done) this long after it started is broken
QUEUE_SLACK_S = 1.0  # past the limit, a query not yet started is refused (a running one ends by itself)
_ERRORS: dict[str, type[FleetError]] = {
    ErrorCode.SQL_NOT_ALLOWED.value: SqlNotAllowedError,
    ErrorCode.INVALID_SQL.value: InvalidSqlError,
    ErrorCode.QUERY_TIMEOUT.value: QueryTimeoutError,
    ErrorCode.RESULT_TOO_LARGE.value: ResultTooLargeError,
    ErrorCode.QUERY_OUT_OF_MEMORY.value: QueryOutOfMemoryError,
    StorageError.code.value: StorageError,
}


@dataclass
class Prepared:
    """What a query needs from the server once the worker said which views it names."""

    # analytics table -> its files, in groups of files with the same columns (`sql.analytics_view`)
    files: dict[str, list[list[str]]] = field(default_factory=dict)
    catalog: dict[str, pa.Table] = field(default_factory=dict)  # catalog view -> its rows


# analytics tables -> what an idle worker reads ahead for them ({"root", "s3", "files"}), or None
ReadAheadPlan = Callable[[tuple[str, ...]], dict[str, Any] | None]


@dataclass
class _Idle:
    """A worker started ahead. Once a query took it, nothing but the query's frames is sent to it."""

    proc: subprocess.Popen[bytes]
    lock: threading.Lock = field(default_factory=threading.Lock)
    taken: bool = False


class SqlPool:
    def __init__(self, limits: Limits, httpfs: bool, read_ahead: ReadAheadPlan | None = None) -> None:
        self.limits = limits
        self._httpfs = httpfs
        self._read_ahead = read_ahead
        self._workdir = tempfile.mkdtemp(prefix="fleet-sql-")  # the workers' HOME, cwd and spill folder
        self._executor = ThreadPoolExecutor(limits.workers, thread_name_prefix="fleet-sql")
        self._planner = ThreadPoolExecutor(1, thread_name_prefix="fleet-sql-read-ahead")
        self._lock = threading.Lock()
        self._idle: list[_Idle] = []
        self._recent: tuple[str, ...] = ()  # the analytics tables the last query that read any named
        self._admitted = 0
        self._closed = False
        atexit.register(self.close)

    @property
    def workdir(self) -> str:
        return self._workdir

    @property
    def admitted(self) -> int:
        """Queries running or waiting now."""
        return self._admitted

    async def run(self, request: dict[str, Any], prepare: Callable[[set[str]], Prepared]) -> pa.Table:
        """The answer to `request` (query, root, s3, hidden), waiting without holding any thread;
        refused (429) if it is still queued when its time limit falls."""
        future = self.submit(request, prepare)
        waiting = asyncio.wrap_future(future)
        try:
            return await asyncio.wait_for(asyncio.shield(waiting), self.limits.seconds + QUEUE_SLACK_S)
        except TimeoutError:
            if future.cancel():  # never left the queue
                raise self._waited_too_long(self.limits.seconds) from None
            return await waiting  # running: its own deadline (the same limit) ends it at once
        except asyncio.CancelledError:
            future.cancel()  # the caller went away (shield kept it from doing so): a queued query never runs
            raise

    def _waited_too_long(self, waited_s: float) -> SqlBusyError:
        return SqlBusyError(
            f"the query waited {waited_s:.1f} s for a SQL worker, its whole time limit (FLEET_SQL_TIMEOUT_S="
            f"{self.limits.seconds:g}, counted from its arrival), while FLEET_SQL_WORKERS={self.limits.workers} "
            "queries ran: retry in a few seconds",
            retry_after_s=math.ceil(min(self.limits.seconds, 30.0)),
        )

    def submit(self, request: dict[str, Any], prepare: Callable[[set[str]], Prepared]) -> Future[pa.Table]:
        with self._lock:
            if self._admitted >= self.limits.workers + self.limits.queue:
                raise SqlBusyError(
                    f"{self._admitted} SQL queries are running or waiting, the most this server "
                    f"takes (FLEET_SQL_WORKERS={self.limits.workers} running, FLEET_SQL_QUEUE="
                    f"{self.limits.queue} waiting): retry in a few seconds"
                )
            self._admitted += 1
        arrived = time.monotonic()  # the time limit counts from here: the queue is part of the wait
        future = self._executor.submit(self._run, {**request, "limits": asdict(self.limits)}, prepare, arrived)
        future.add_done_callback(self._release)  # also when cancelled before it started
        return future

    def _release(self, _: Future[pa.Table]) -> None:
        with self._lock:
            self._admitted -= 1

    def _run(self, request: dict[str, Any], prepare: Callable[[set[str]], Prepared], arrived: float) -> pa.Table:
        deadline = arrived + self.limits.seconds
        if time.monotonic() >= deadline:  # its limit fell while it waited: it never runs
            raise self._waited_too_long(time.monotonic() - arrived)
        proc = self._take()
        try:
            waited = time.monotonic()
            _Conversation(proc, waited + START_S, self.limits).receive_json()  # ready
            # A worker still starting (its imports, about a second after a query was killed) is the
            # depot's cost, not the query's: the limit is moved by that wait, not spent on it.
            deadline += time.monotonic() - waited
            talk = _Conversation(proc, deadline, self.limits)
            talk.send(json.dumps(request).encode())
            named = talk.receive_json()["tables"]
            self._recent = tuple(t for t in named if t in ANALYTICS_VIEWS) or self._recent
            prepared = prepare(set(named))
            talk.send(json.dumps({"files": prepared.files, "catalog": list(prepared.catalog)}).encode())
            for table in prepared.catalog.values():
                talk.send(worker.ipc_bytes(table))
            talk.receive_json()
            answer = talk.receive(self.limits.memory_bytes)
            try:  # the sandbox's answer: as untrusted as the SQL that made it, so validated in full
                return untrusted.read_table(answer)
            except RrdError as exc:
                raise InternalError(f"the SQL worker answered with no valid table ({exc.detail})") from exc
        finally:
            _stop(proc)
            self.start()  # the next one starts now, not during the query: its imports would slow it

    def _take(self) -> subprocess.Popen[bytes]:
        """An idle worker, else a new one."""
        while True:
            with self._lock:
                if not self._idle:
                    return self._spawn()
                candidate = self._idle.pop(0)
            with candidate.lock:  # waits for a read-ahead frame being sent: it must not split the query's
                candidate.taken = True
            if candidate.proc.poll() is None:
                return candidate.proc

    def _spawn(self) -> subprocess.Popen[bytes]:
        root = str(Path(services.__file__).resolve().parent.parent)  # where `services` is importable from
        env = {
            "PATH": os.defpath,
            "HOME": self._workdir,
            "TMPDIR": self._workdir,
            "LANG": "C.UTF-8",
            "PYTHONPATH": root,
            "PYTHONNOUSERSITE": "1",
            "PYTHONDONTWRITEBYTECODE": "1",
        }
        argv = [sys.executable, "-m", "services.analytics.worker"] + (["--httpfs"] if self._httpfs else [])
        return subprocess.Popen(
            argv,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=env,
            cwd=self._workdir,
            start_new_session=True,
        )

    def start(self) -> None:
        """Start idle workers up to one per running slot (the first query's end does it, else), each
        told what to read ahead once the tables of the last query are planned (in a thread of its own:
        planning reads the lakehouse's metadata, and the query that ended is still answering)."""
        with self._lock:
            while len(self._idle) < self.limits.workers and not self._closed:
                idle = _Idle(self._spawn())
                self._idle.append(idle)
                if self._read_ahead is not None and self._recent:
                    self._planner.submit(self._send_read_ahead, idle, self._recent)

    def _send_read_ahead(self, idle: _Idle, tables: tuple[str, ...]) -> None:
        assert self._read_ahead is not None
        try:
            plan = self._read_ahead(tables)
        except Exception as exc:  # the query will plan (and fail, if it must) by itself
            log.debug("no read-ahead for %s: %s", tables, exc)
            return
        if not plan:
            return
        frame = json.dumps({"read_ahead": plan}).encode()
        with idle.lock:
            if idle.taken or idle.proc.stdin is None:
                return
            with contextlib.suppress(OSError, ValueError):  # it was stopped meanwhile
                worker.write_frame(idle.proc.stdin, frame)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for each in idle:
            _stop(each.proc)
        self._executor.shutdown(wait=False, cancel_futures=True)
        self._planner.shutdown(wait=False, cancel_futures=True)
        shutil.rmtree(self._workdir, ignore_errors=True)


class _Conversation:
    """Frames to and from one worker; every wait for an answer watches the clock and the memory."""

    def __init__(self, proc: subprocess.Popen[bytes], deadline: float, limits: Limits) -> None:
        assert proc.stdin is not None and proc.stdout is not None
        self.proc, self.deadline, self.limits = proc, deadline, limits
        self._in, self._out = proc.stdin, proc.stdout.fileno()
        self._memory = limits.memory_bytes

    def send(self, data: bytes) -> None:
        try:
            worker.write_frame(self._in, data)
        except (BrokenPipeError, OSError):
            raise self._ended() from None

    def receive_json(self) -> dict[str, Any]:
        reply: dict[str, Any] = json.loads(self.receive(1 << 20))
        if "error" in reply:
            error = reply["error"]
            raise _ERRORS.get(error["code"], FleetError)(error["message"])
        return reply

    def receive(self, most: int) -> bytes:
        (size,) = worker._LENGTH.unpack(self._read(worker._LENGTH.size))
        if size > most:
            _stop(self.proc)
            raise ResultTooLargeError(
                f"the answer is larger than {self.limits.memory} (FLEET_SQL_MEMORY_LIMIT): "
                "select fewer or shorter columns, aggregate, or add a LIMIT"
            )
        return self._read(size)

    def _read(self, size: int) -> bytes:
        parts, need = [], size
        while need:
            self._check()
            ready, _, _ = select.select([self._out], [], [], max(0.0, min(POLL_S, self.deadline - time.monotonic())))
            if not ready:
                continue
            part = os.read(self._out, min(need, 1 << 20))
            if not part:
                raise self._ended()
            parts.append(part)
            need -= len(part)
        return b"".join(parts)

    def _check(self) -> None:
        if time.monotonic() >= self.deadline:
            _stop(self.proc)
            raise QueryTimeoutError(
                f"the query ran longer than {self.limits.seconds:g} s (FLEET_SQL_TIMEOUT_S): "
                "filter by robot_id and date to read fewer files, or aggregate less"
            )
        if worker.resident_bytes(self.proc.pid) > self._memory:
            _stop(self.proc)
            raise QueryOutOfMemoryError(out_of_memory(self.limits))

    def _ended(self) -> FleetError:
        code = self.proc.wait()
        if code == -signal.SIGKILL:  # the kernel's OOM killer: the memory limit is above what the host has
            return QueryOutOfMemoryError(out_of_memory(self.limits, "the host ran out of memory"))
        log.warning("a SQL worker exited with status %s", code)
        return FleetError(f"the SQL worker stopped unexpectedly (exit status {code})")


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait()
    for pipe in (proc.stdin, proc.stdout):
        if pipe is not None:
            with contextlib.suppress(OSError):
                pipe.close()
