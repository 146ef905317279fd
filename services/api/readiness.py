"""What `/readyz` checks: the catalog answers a query and the hot disk takes a write.

Each check runs on a thread of its own with a short time limit: a database or a disk that hangs
makes the node not ready instead of hanging the probe or the event loop. A check still hung from
an earlier probe is not started again (probes must not pile up threads): it answers "no answer"
until it returns.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import shutil
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

CHECK_TIMEOUT_S = 2.0
OK = "ok"


class Check:
    """One readiness check: a function that returns when the part is ready and raises otherwise."""

    def __init__(self, name: str, probe: Callable[[], None]) -> None:
        self.name = name
        self._probe = probe
        self._running: concurrent.futures.Future[None] | None = None
        self._guard = threading.Lock()

    def _start(self) -> concurrent.futures.Future[None]:
        with self._guard:
            if self._running is None or self._running.done():
                future: concurrent.futures.Future[None] = concurrent.futures.Future()
                self._running = future
                # A daemon thread, not a pool's: one that hangs must neither hold a pool's worker
                # nor keep the process from exiting.
                threading.Thread(target=self._run, args=(future,), name=f"readyz-{self.name}", daemon=True).start()
            return self._running

    def _run(self, future: concurrent.futures.Future[None]) -> None:
        try:
            self._probe()
        except Exception as exc:
            future.set_exception(exc)
        else:
            future.set_result(None)

    async def status(self, timeout: float = CHECK_TIMEOUT_S) -> str:
        """`ok`, or what is wrong in one line."""
        try:
            # shield: the time limit stops the wait, not the check (a thread cannot be stopped)
            await asyncio.wait_for(asyncio.shield(asyncio.wrap_future(self._start())), timeout)
        except TimeoutError:
            return f"no answer within {timeout:g} s"
        except Exception as exc:
            return _one_line(exc)
        return OK


def catalog_check(catalog: sessionmaker[Session]) -> Check:
    def probe() -> None:
        with catalog() as session:
            session.execute(sa.text("SELECT 1"))

    return Check("catalog", probe)


def hot_disk_check(root: Path, min_free_bytes: int) -> Check:
    def probe() -> None:
        # An unnamed file where the system allows it (O_TMPFILE): nothing is left behind if the
        # process stops here. Unbuffered, so the write reaches the file system now.
        with tempfile.TemporaryFile(dir=root, buffering=0) as probe_file:
            probe_file.write(b"\0")
        free = shutil.disk_usage(root).free
        if free < min_free_bytes:
            raise OSError(
                f"{root} has {free} bytes free, below FLEET_MIN_FREE_BYTES ({min_free_bytes}): new data is refused"
            )

    return Check("hot_disk", probe)


async def check_all(checks: list[Check]) -> dict[str, str]:
    """Each check's status by name, the checks run at once."""
    statuses = await asyncio.gather(*(check.status() for check in checks))
    return {check.name: status for check, status in zip(checks, statuses, strict=True)}


def _one_line(exc: Exception) -> str:
    # SQLAlchemy's messages go on with the statement and a link to its docs: the driver's first
    # line says what happened.
    cause = exc.orig if isinstance(exc, sa.exc.DBAPIError) and exc.orig is not None else exc
    text = str(cause).strip().splitlines()[0] if str(cause).strip() else ""
    return f"{type(cause).__name__}: {text}"[:300]
