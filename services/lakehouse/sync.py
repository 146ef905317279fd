"""Copying runs' analytics rows into the Iceberg tables: exactly one copy per run, ever.

The sync job takes the runs the catalog marks pending (`catalog.lakehouse`), a batch at a time, and
per table commits once: the batch's old rows deleted and their rows now appended, in one Iceberg
transaction. A run sealed again, extracted again or deleted is replaced or removed, never doubled,
and a commit that loses to another node's is made again on the table as that commit left it.
Rows are read from each run's Parquet file in the warm store by ranged reads, a row group at a time,
so memory does not grow with the run.
"""

from __future__ import annotations

import datetime as dt
import logging
import time
import uuid
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pyarrow as pa
import pyarrow.parquet as pq
from pyiceberg.exceptions import CommitFailedException, ValidationException
from pyiceberg.expressions import In
from pyiceberg.io.pyarrow import _dataframe_to_data_files
from sqlalchemy.orm import Session, sessionmaker

from catalog import lakehouse as marks
from catalog.db import session_scope
from catalog.lakehouse import PendingRun
from catalog.sql_tables import catalog_tables, sql_columns
from services.lakehouse.schemas import CATALOG, MAX_COLUMNS, RUN_COLUMN, TELEMETRY, iceberg_rows
from services.lakehouse.tables import Lakehouse
from services.storage.objectstore import ObjectFile, ObjectStore

log = logging.getLogger(__name__)

JOB = "lakehouse.sync"
BATCH_RUNS = 32  # runs per commit: fewer commits (and snapshots) than one per run, bounded work
JOB_BATCHES = 16  # batches one pass of the job copies at most: the rest wait for the next pass
PIECE_ROWS = 1 << 20  # rows held at a time while appending a run
COMMIT_ATTEMPTS = 6


@dataclass(frozen=True)
class SyncReport:
    runs: int  # copied (their rows replaced)
    removed: int  # deleted runs whose rows left the tables
    rows: int
    left: int  # still pending after this pass (more than a batch, or changed meanwhile)


def sync(
    lake: Lakehouse,
    catalog: sessionmaker[Session],
    warm: ObjectStore,
    clock: Callable[[], dt.datetime],
    batches: int | None = None,
    progress: Callable[[SyncReport], None] | None = None,
    only: list[str] | None = None,
) -> SyncReport:
    """Copy pending runs (of `only`, if given), a batch at a time, until none is left (or after
    `batches` batches)."""
    total = SyncReport(0, 0, 0, 0)
    done_batches = 0
    while batches is None or done_batches < batches:
        with session_scope(catalog) as session:
            batch = marks.pending(session, BATCH_RUNS, only)
        if not batch:
            break
        rows = copy_batch(lake, catalog, warm, batch)
        with session_scope(catalog, write=True) as session:
            still = sum(not marks.done(session, run.run_id, run.wanted, rows.get(run.run_id), clock()) for run in batch)
        total = SyncReport(
            total.runs + sum(not r.gone for r in batch),
            total.removed + sum(r.gone for r in batch),
            total.rows + sum(rows.values()),
            0,
        )
        done_batches += 1
        if progress is not None:
            progress(total)
        if still == len(batch):  # every run changed while it was copied: the next pass takes them
            break
    with session_scope(catalog) as session:
        left = marks.pending_count(session)
    return SyncReport(total.runs, total.removed, total.rows, left)


def copy_now(
    lake: Lakehouse | None,
    catalog: sessionmaker[Session],
    warm: ObjectStore,
    clock: Callable[[], dt.datetime],
    run_ids: list[str],
) -> None:
    """Copy these runs now, as their writer (sealing, extraction, deletion) has just changed them, so
    SQL over the tables sees the change at once; a failure leaves them to the job, which tries again."""
    if lake is None:
        return
    try:
        sync(lake, catalog, warm, clock, only=run_ids)
    except Exception as exc:
        log.warning("lakehouse: runs %s left for the next sync (%s: %s)", ", ".join(run_ids), type(exc).__name__, exc)


def copy_batch(
    lake: Lakehouse, catalog: sessionmaker[Session], warm: ObjectStore, batch: list[PendingRun]
) -> dict[str, int]:
    """Replace the batch's rows in every table: its catalog rows as the catalog holds them now, and
    the telemetry of runs whose analytics files changed (or that are gone); returns those runs'
    telemetry row counts, all tables."""
    telemetry = [run for run in batch if run.telemetry or run.gone]
    rows = {run.run_id: 0 for run in telemetry}
    for name in TELEMETRY if telemetry else ():
        for run_id, n in replace_rows(lake, name, warm, telemetry).items():
            rows[run_id] += n
    ids = [run.run_id for run in batch]
    for name in CATALOG:
        _replace_catalog_rows(lake, catalog, name, ids)
    return rows


def _replace_catalog_rows(lake: Lakehouse, catalog: sessionmaker[Session], name: str, ids: list[str]) -> None:
    """The runs' rows of catalog table `name`, as the catalog holds them now, in place of the old."""
    column = RUN_COLUMN[name]
    with session_scope(catalog) as session:
        held = catalog_tables(session, [name], {name: dict(sql_columns(name))[column].in_(ids)})[name]

    def pieces(columns: set[str]) -> Iterator[pa.Table]:
        if held.num_rows:
            yield held.select([c for c in held.column_names if c in columns])

    _replace(lake, name, column, ids, pieces)


def replace_rows(lake: Lakehouse, name: str, warm: ObjectStore, batch: list[PendingRun]) -> dict[str, int]:
    """One commit on telemetry table `name`: the batch's runs' rows deleted, then their files' rows
    appended; returns each run's rows."""
    sources = [(run, run.files[name]) for run in batch if name in run.files and not run.gone]
    _add_columns(lake, name, warm, sources)
    counts: dict[str, int] = {}

    def pieces(columns: set[str]) -> Iterator[pa.Table]:
        counts.clear()
        for run, key in sources:
            for piece in _pieces(warm, key, run, name, columns):
                counts[run.run_id] = counts.get(run.run_id, 0) + piece.num_rows
                yield piece

    _replace(lake, name, "run_id", [run.run_id for run in batch], pieces)
    return counts


def _replace(
    lake: Lakehouse, name: str, column: str, ids: list[str], pieces: Callable[[set[str]], Iterator[pa.Table]]
) -> None:
    """One commit on table `name`: rows whose `column` is one of `ids` deleted, then `pieces` (given
    the table's columns, made again for each attempt) appended; a commit lost to another writer is
    made again on the table as that writer left it."""
    for attempt in range(COMMIT_ATTEMPTS):
        table = lake.table(name)
        try:
            with table.transaction() as tx, warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "Delete operation did not match any records": a new run
                tx.delete(In(column, ids))  # type: ignore[call-arg,arg-type]  # pydantic model: mypy misreads it
                with tx.update_snapshot().merge_append() as append:
                    for piece in pieces(set(tx.table_metadata.schema().column_names)):
                        for data_file in _dataframe_to_data_files(
                            table_metadata=tx.table_metadata,
                            write_uuid=uuid.uuid4(),  # names its files: one per piece, never reused
                            df=piece,
                            io=table.io,
                        ):
                            append.append_data_file(data_file)
            return
        except (CommitFailedException, ValidationException) as exc:
            if attempt == COMMIT_ATTEMPTS - 1:
                raise
            log.info("lakehouse %s: commit lost to another writer (%s), trying again", name, exc)
            time.sleep(0.05 * 2**attempt)


def _pieces(warm: ObjectStore, key: str, run: PendingRun, name: str, columns: set[str]) -> Iterator[pa.Table]:
    """The run's rows of one table from its Parquet file, up to PIECE_ROWS at a time, as the table
    holds them (a timeline the table has no column for is left out)."""
    assert run.robot_id is not None and run.date is not None
    parquet = pq.ParquetFile(ObjectFile(warm, key, warm.head(key).size))  # type: ignore[arg-type]
    for batch in parquet.iter_batches(batch_size=PIECE_ROWS):
        rows = iceberg_rows(name, batch, run.robot_id, run.date)
        dropped = [c for c in rows.column_names if c not in columns]
        yield rows.drop_columns(dropped) if dropped else rows


def _add_columns(lake: Lakehouse, name: str, warm: ObjectStore, sources: list[tuple[PendingRun, str]]) -> None:
    """Timelines the batch brings that the table has no column for yet become columns (up to
    MAX_COLUMNS), committed before the rows so the data commit never races a schema change."""
    table = lake.table(name)
    held = set(table.schema().column_names)
    wanted: dict[str, pa.Field] = {}
    for run, key in sources:
        assert run.robot_id is not None and run.date is not None
        arrow = pq.read_schema(ObjectFile(warm, key, warm.head(key).size))  # type: ignore[arg-type]
        empty = pa.RecordBatch.from_pylist([], schema=arrow)
        for fld in iceberg_rows(name, empty, run.robot_id, run.date).schema:
            if fld.name not in held and fld.name not in wanted:
                wanted[fld.name] = fld.with_nullable(True)
    room = MAX_COLUMNS - len(held)
    if not wanted or room <= 0:
        return
    new = list(wanted.values())[:room]
    for attempt in range(COMMIT_ATTEMPTS):
        try:
            with table.update_schema() as update:
                update.union_by_name(pa.schema(new))
            return
        except CommitFailedException:
            if attempt == COMMIT_ATTEMPTS - 1:
                raise
            table = lake.table(name)
