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
from services.lakehouse.schemas import MAX_COLUMNS, TELEMETRY, iceberg_rows
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
        rows = copy_batch(lake, warm, batch)
        with session_scope(catalog, write=True) as session:
            still = sum(
                not marks.done(session, run.run_id, run.wanted, rows.get(run.run_id, 0), clock()) for run in batch
            )
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


def copy_batch(lake: Lakehouse, warm: ObjectStore, batch: list[PendingRun]) -> dict[str, int]:
    """Replace the batch's rows in every table; returns each run's row count, all tables."""
    rows = {run.run_id: 0 for run in batch}
    for name in TELEMETRY:
        for run_id, n in replace_rows(lake, name, warm, batch).items():
            rows[run_id] += n
    return rows


def replace_rows(lake: Lakehouse, name: str, warm: ObjectStore, batch: list[PendingRun]) -> dict[str, int]:
    """One commit on table `name`: the batch's runs' rows deleted, then their files' rows appended."""
    sources = [(run, run.files[name]) for run in batch if name in run.files]
    _add_columns(lake, name, warm, sources)
    ids = [run.run_id for run in batch]
    for attempt in range(COMMIT_ATTEMPTS):
        table = lake.table(name)
        counts = dict.fromkeys(ids, 0)
        try:
            with table.transaction() as tx, warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "Delete operation did not match any records": a new run
                tx.delete(In("run_id", ids))  # type: ignore[call-arg,arg-type]  # pydantic model: mypy misreads it
                if sources:
                    with tx.update_snapshot().merge_append() as append:
                        columns = set(tx.table_metadata.schema().column_names)
                        for run, key in sources:
                            for piece in _pieces(warm, key, run, name, columns):
                                counts[run.run_id] += piece.num_rows
                                for data_file in _dataframe_to_data_files(
                                    table_metadata=tx.table_metadata,
                                    write_uuid=uuid.uuid4(),  # names its files: one per piece, never reused
                                    df=piece,
                                    io=table.io,
                                ):
                                    append.append_data_file(data_file)
            return counts
        except (CommitFailedException, ValidationException) as exc:
            if attempt == COMMIT_ATTEMPTS - 1:
                raise
            log.info("lakehouse %s: commit lost to another writer (%s), trying again", name, exc)
            time.sleep(0.05 * 2**attempt)
    raise AssertionError("unreachable")


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
