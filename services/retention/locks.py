"""One job at a time across service processes: a Postgres advisory lock per job name.

An embedded DuckDB catalog has a single writer process, so a lock inside the process suffices.
The lock is held on a connection of its own for as long as the job runs and is released when
that connection ends, so a process that dies holding it frees it.
"""

from __future__ import annotations

import threading
import zlib
from collections.abc import Iterator
from contextlib import contextmanager

import sqlalchemy as sa

_LOCAL: dict[str, threading.Lock] = {}
_LOCAL_GUARD = threading.Lock()
_NAMESPACE = 0x466C7400  # "Flt\0": keeps our advisory lock keys apart from other users of the database


def lock_key(job: str) -> int:
    return _NAMESPACE ^ zlib.crc32(job.encode())


@contextmanager
def job_lock(engine: sa.Engine, job: str) -> Iterator[bool]:
    """Yields True if this process now holds the job's lock, False if another one does."""
    if engine.dialect.name != "postgresql":
        with _LOCAL_GUARD:
            lock = _LOCAL.setdefault(f"{engine.url}:{job}", threading.Lock())
        got = lock.acquire(blocking=False)
        try:
            yield got
        finally:
            if got:
                lock.release()
        return
    with engine.connect() as conn:
        got = bool(conn.execute(sa.select(sa.func.pg_try_advisory_lock(lock_key(job)))).scalar())
        conn.commit()
        try:
            yield got
        finally:
            if got:
                conn.execute(sa.select(sa.func.pg_advisory_unlock(lock_key(job))))
                conn.commit()
