"""What the agent must remember across restarts, in one SQLite file in the spool (`agent.db`).

The spool's run files are the data; this holds where forwarding stands for each run (how far the
depot is known to hold it, and how far it is known to be sealed there), the progress of watched
files, the MCAP files uploaded (or refused), the pulls being served and the link's state. Every
write is its own transaction (WAL mode), so a kill -9 at any moment leaves the last state written:
at worst the agent asks the depot again about chunks it had already learnt it holds, never forgets
one it has not.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

STATE_FILE = "agent.db"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY,
    checked_until INTEGER NOT NULL,  -- every forwarded message before this offset is held by the depot
    confirmed_until INTEGER NOT NULL,  -- ... and sealed in its warm tier
    confirmed INTEGER NOT NULL DEFAULT 0,  -- the whole run is (the robot may delete it)
    depot_tier TEXT,
    local_only_chunks INTEGER NOT NULL DEFAULT 0,
    local_only_bytes INTEGER NOT NULL DEFAULT 0,
    updated_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS files (path TEXT PRIMARY KEY, progress TEXT NOT NULL, updated_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS pulls (
    pull_id TEXT PRIMARY KEY,
    run_id TEXT NOT NULL,
    state TEXT NOT NULL,
    chunks_sent INTEGER NOT NULL DEFAULT 0,
    bytes_sent INTEGER NOT NULL DEFAULT 0,
    spec TEXT NOT NULL,
    updated_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS facts (key TEXT PRIMARY KEY, value TEXT NOT NULL, updated_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS bags (
    path TEXT PRIMARY KEY,
    run_id TEXT NOT NULL,
    application TEXT NOT NULL,
    inode INTEGER NOT NULL,  -- the file as it was sent (or refused): another inode, size or mtime is sent again
    size INTEGER NOT NULL,
    mtime_ns INTEGER NOT NULL,
    state TEXT NOT NULL,  -- uploaded | failed
    import_id TEXT,  -- the depot's id of the import (uploaded)
    error TEXT,  -- the depot's refusal (failed)
    updated_at REAL NOT NULL
);
"""


@dataclass
class RunState:
    run_id: str
    checked_until: int = 0
    confirmed_until: int = 0
    confirmed: bool = False
    depot_tier: str | None = None
    local_only_chunks: int = 0
    local_only_bytes: int = 0


@dataclass
class PullState:
    pull_id: str
    run_id: str
    state: str  # pending | sending | done | failed (as the depot says)
    spec: dict[str, Any] = field(default_factory=dict)
    chunks_sent: int = 0
    bytes_sent: int = 0


@dataclass
class BagRecord:
    """A watched MCAP file the depot took (`uploaded`) or refused (`failed`), as it was then: the
    same file unchanged is not sent again, across restarts; changed, it is."""

    path: str
    run_id: str
    application: str
    inode: int
    size: int
    mtime_ns: int
    state: str  # uploaded | failed
    import_id: str | None = None
    error: str | None = None


class AgentState:
    """The agent's SQLite state. Safe to call from any thread (one connection behind a lock)."""

    def __init__(self, spool: Path, *, readonly: bool = False) -> None:
        path = spool / STATE_FILE
        if readonly:
            self._db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, check_same_thread=False)
        else:
            spool.mkdir(parents=True, exist_ok=True)
            self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")  # WAL: a commit survives a process kill
            self._db.executescript(_SCHEMA)
        self._lock = threading.Lock()

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def _all(self, sql: str, *args: Any) -> list[tuple[Any, ...]]:
        with self._lock:
            return self._db.execute(sql, args).fetchall()

    def _write(self, sql: str, *args: Any) -> None:
        with self._lock:
            self._db.execute(sql, args)

    # --- runs -------------------------------------------------------------------------------

    def runs(self) -> dict[str, RunState]:
        rows = self._all(
            "SELECT run_id, checked_until, confirmed_until, confirmed, depot_tier, local_only_chunks, "
            "local_only_bytes FROM runs"
        )
        return {row[0]: RunState(row[0], row[1], row[2], bool(row[3]), *row[4:]) for row in rows}

    def save_run(self, run: RunState) -> None:
        self._write(
            "INSERT INTO runs (run_id, checked_until, confirmed_until, confirmed, depot_tier, local_only_chunks, "
            "local_only_bytes, updated_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (run_id) DO UPDATE SET "
            "checked_until = excluded.checked_until, confirmed_until = excluded.confirmed_until, "
            "confirmed = excluded.confirmed, depot_tier = excluded.depot_tier, "
            "local_only_chunks = excluded.local_only_chunks, local_only_bytes = excluded.local_only_bytes, "
            "updated_at = excluded.updated_at",
            run.run_id,
            run.checked_until,
            run.confirmed_until,
            int(run.confirmed),
            run.depot_tier,
            run.local_only_chunks,
            run.local_only_bytes,
            time.time(),
        )

    def forget_run(self, run_id: str) -> None:
        self._write("DELETE FROM runs WHERE run_id = ?", run_id)

    # --- watched files ------------------------------------------------------------------------

    def file_progress(self) -> dict[str, dict[str, Any]]:
        return {path: json.loads(progress) for path, progress in self._all("SELECT path, progress FROM files")}

    def save_file(self, path: str, progress: dict[str, Any]) -> None:
        self._write(
            "INSERT INTO files (path, progress, updated_at) VALUES (?, ?, ?) ON CONFLICT (path) DO UPDATE SET "
            "progress = excluded.progress, updated_at = excluded.updated_at",
            path,
            json.dumps(progress),
            time.time(),
        )

    def forget_file(self, path: str) -> None:
        self._write("DELETE FROM files WHERE path = ?", path)

    # --- pulls --------------------------------------------------------------------------------

    def pulls(self) -> dict[str, PullState]:
        rows = self._all("SELECT pull_id, run_id, state, spec, chunks_sent, bytes_sent FROM pulls")
        return {r[0]: PullState(r[0], r[1], r[2], json.loads(r[3]), r[4], r[5]) for r in rows}

    def save_pull(self, pull: PullState) -> None:
        self._write(
            "INSERT INTO pulls (pull_id, run_id, state, chunks_sent, bytes_sent, spec, updated_at) "
            "VALUES (?, ?, ?, ?, ?, ?, ?) ON CONFLICT (pull_id) DO UPDATE SET state = excluded.state, "
            "chunks_sent = excluded.chunks_sent, bytes_sent = excluded.bytes_sent, spec = excluded.spec, "
            "updated_at = excluded.updated_at",
            pull.pull_id,
            pull.run_id,
            pull.state,
            pull.chunks_sent,
            pull.bytes_sent,
            json.dumps(pull.spec),
            time.time(),
        )

    def forget_pull(self, pull_id: str) -> None:
        self._write("DELETE FROM pulls WHERE pull_id = ?", pull_id)

    # --- watched MCAP files (rosbag2 bags) --------------------------------------------------------

    def bags(self) -> dict[str, BagRecord]:
        try:
            rows = self._all(
                "SELECT path, run_id, application, inode, size, mtime_ns, state, import_id, error FROM bags"
            )
        except sqlite3.OperationalError as exc:
            # A read-only handle (`fleet agent status`) on a state file an older agent wrote, which
            # has no such table yet: it has no bags. Anything else is a real fault.
            if "no such table" not in str(exc):
                raise
            return {}
        return {row[0]: BagRecord(*row) for row in rows}

    def save_bag(self, bag: BagRecord) -> None:
        self._write(
            "INSERT INTO bags (path, run_id, application, inode, size, mtime_ns, state, import_id, error, updated_at) "
            "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (path) DO UPDATE SET run_id = excluded.run_id, "
            "application = excluded.application, inode = excluded.inode, size = excluded.size, "
            "mtime_ns = excluded.mtime_ns, state = excluded.state, import_id = excluded.import_id, "
            "error = excluded.error, updated_at = excluded.updated_at",
            bag.path,
            bag.run_id,
            bag.application,
            bag.inode,
            bag.size,
            bag.mtime_ns,
            bag.state,
            bag.import_id,
            bag.error,
            time.time(),
        )

    def forget_bag(self, path: str) -> None:
        self._write("DELETE FROM bags WHERE path = ?", path)

    # --- facts (the link's state, the running agent's heartbeat) -----------------------------------

    def set_fact(self, key: str, value: Any) -> None:
        self._write(
            "INSERT INTO facts (key, value, updated_at) VALUES (?, ?, ?) ON CONFLICT (key) DO UPDATE SET "
            "value = excluded.value, updated_at = excluded.updated_at",
            key,
            json.dumps(value),
            time.time(),
        )

    def facts(self) -> dict[str, tuple[Any, float]]:
        """Each fact with when it was written (seconds since the epoch)."""
        return {
            key: (json.loads(value), at) for key, value, at in self._all("SELECT key, value, updated_at FROM facts")
        }


def run_state_dict(run: RunState) -> dict[str, Any]:
    return asdict(run)
