"""What an idle SQL worker reads ahead: the footers of the lakehouse files the next query will likely
read, so that query finds them parsed (and each file's size known) instead of asking the store.

A query's own cost on a table of many files is mostly fixed: a HEAD and a footer per file before the
first row, paid again by every query since each runs in a fresh process. An idle worker pays them
while it waits, on a cursor of its own, and stops the moment the query arrives (what it read by then
is kept, the rest is read by the query as before). Only the lakehouse's data files are read ahead:
Iceberg never rewrites a data file under the same name, so what was cached cannot go stale (a run's
per-run Parquet file is rewritten in place when it is extracted again). The query still reads exactly
the files of its own snapshot: the cache holds footers and sizes, never which files a table has.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from typing import Any

import duckdb

from services.analytics import sql

log = logging.getLogger(__name__)
STOP_WAIT_S = 0.5  # how long a query waits for an interrupted read-ahead to give the cursor back


class ReadAhead:
    """Reads the footers of `files` (lakehouse data files: paths or s3:// URLs under `root`) on a
    cursor of `con`'s database, in a thread, until done or `stop`."""

    def __init__(self, con: duckdb.DuckDBPyConnection, root: str, s3: dict[str, Any] | None, files: list[str]) -> None:
        self._cursor = con.cursor()  # same database, so the same caches; a connection of its own to interrupt
        self._thread = threading.Thread(target=self._read, args=(root, s3, files), name="read-ahead", daemon=True)
        self._thread.start()

    def _read(self, root: str, s3: dict[str, Any] | None, files: list[str]) -> None:
        try:
            sql.cache_settings(self._cursor)
            if root.startswith("s3://"):
                sql.s3_secret(self._cursor, sql.S3Access(**s3) if s3 else None, root)
            self._cursor.execute(f"SELECT count(*) FROM parquet_file_metadata([{sql.listed(files)}])").fetchall()
        except Exception as exc:  # a read-ahead is an optimisation: the query reads what is missing
            log.debug("read-ahead stopped: %s", sql.first_line(exc))

    def stop(self) -> None:
        """Interrupt what is left, and give the read-ahead a moment to let go of the database."""
        with contextlib.suppress(Exception):
            self._cursor.interrupt()
        self._thread.join(STOP_WAIT_S)

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()
