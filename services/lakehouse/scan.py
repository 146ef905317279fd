"""What a reader of the lakehouse reads: a table's data files as of its current snapshot.

The depot's SQL plans here (pyiceberg reads the snapshot's manifests) and hands its sandboxed
DuckDB the list, as it hands it the catalog's list of per-run files otherwise; the plan is kept
until the table's next commit. The depot writes copy-on-write (a replaced run's files are
rewritten or dropped, never masked by delete files), so the data files are the table's rows.
"""

from __future__ import annotations

import threading
from urllib.parse import unquote, urlparse

from cachetools import LRUCache

from core.errors import UnavailableError
from services.lakehouse.tables import Lakehouse

# (table, metadata file) -> its data files, in groups of files with the same columns
_plans: LRUCache[tuple[str, str], tuple[tuple[str, ...], ...]] = LRUCache(maxsize=64)
_lock = threading.Lock()


def data_files(lake: Lakehouse, name: str) -> list[list[str]]:
    """Table `name`'s data files now, as DuckDB names them (a path, or an s3:// URL), in groups of
    files that hold the same columns (as the manifests' column counts say): a reader binds one
    footer per group instead of every file's. Nearly every file of a table is in one group; a file
    the manifests give no counts for is a group of its own."""
    table = lake.table(name)
    key = (name, table.metadata_location)
    with _lock:
        found = _plans.get(key)
    if found is None:
        tasks = list(table.scan().plan_files())
        if any(task.delete_files for task in tasks):
            raise UnavailableError(
                f"the lakehouse table fleet.{name} has row-level delete files, which another writer made: "
                "the depot reads copy-on-write tables only (rewrite it with copy-on-write deletes, or "
                "compact it with `fleet analytics compact`)"
            )
        groups: dict[object, list[str]] = {}
        for task in tasks:
            columns = frozenset(task.file.value_counts or ()) or task.file.file_path
            groups.setdefault(columns, []).append(_duckdb_path(task.file.file_path))
        found = tuple(tuple(group) for group in groups.values())
        with _lock:
            _plans[key] = found
    return [list(group) for group in found]


def _duckdb_path(location: str) -> str:
    parsed = urlparse(location)
    return unquote(parsed.path) if parsed.scheme == "file" else location


def root(lake: Lakehouse) -> str:
    """The lakehouse's folder as DuckDB names it."""
    return _duckdb_path(lake.warehouse)
