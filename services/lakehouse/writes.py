"""Writing a batch of runs into the Iceberg tables: per table one commit that deletes the runs' old
rows and appends their rows now (`services.lakehouse.sync` decides which runs, and when).

A table the batch brings nothing to and holds nothing of gets no commit at all (no empty snapshot):
a sealed run with scalars and nothing else costs two commits, not seven. Each run's Parquet
file is opened once per batch (its size and footer), however often a lost commit is made again.
"""

from __future__ import annotations

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

from catalog.db import session_scope
from catalog.lakehouse import PendingRun
from catalog.sql_tables import catalog_tables, sql_columns
from services.lakehouse.schemas import CATALOG, MAX_COLUMNS, RUN_COLUMN, TELEMETRY, iceberg_rows
from services.lakehouse.tables import Lakehouse
from services.storage.objectstore import ObjectFile, ObjectStore

log = logging.getLogger(__name__)

PIECE_ROWS = 1 << 20  # rows held at a time while appending a run
COMMIT_ATTEMPTS = 6


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


@dataclass(frozen=True)
class _Source:
    """A run's Parquet file of one table, opened once: its size and footer."""

    run: PendingRun
    key: str
    size: int
    metadata: pq.FileMetaData

    def rows(self, warm: ObjectStore, name: str, columns: set[str]) -> Iterator[pa.Table]:
        """Its rows, up to PIECE_ROWS at a time, as the table holds them (a timeline the table has
        no column for is left out)."""
        assert self.run.robot_id is not None and self.run.date is not None
        parquet = pq.ParquetFile(ObjectFile(warm, self.key, self.size), metadata=self.metadata)  # type: ignore[arg-type]
        for batch in parquet.iter_batches(batch_size=PIECE_ROWS):
            rows = iceberg_rows(name, batch, self.run.robot_id, self.run.date)
            dropped = [c for c in rows.column_names if c not in columns]
            yield rows.drop_columns(dropped) if dropped else rows


def replace_rows(lake: Lakehouse, name: str, warm: ObjectStore, batch: list[PendingRun]) -> dict[str, int]:
    """One commit on telemetry table `name`: the batch's runs' rows deleted, then their files' rows
    appended; returns each run's rows."""
    sources = []
    for run in batch:
        if name in run.files and not run.gone:
            key = run.files[name]
            size = warm.head(key).size
            sources.append(_Source(run, key, size, pq.read_metadata(ObjectFile(warm, key, size))))  # type: ignore[arg-type]
    _add_columns(lake, name, sources)
    counts: dict[str, int] = {}

    def pieces(columns: set[str]) -> Iterator[pa.Table]:
        counts.clear()
        for source in sources:
            for piece in source.rows(warm, name, columns):
                counts[source.run.run_id] = counts.get(source.run.run_id, 0) + piece.num_rows
                yield piece

    _replace(lake, name, "run_id", [run.run_id for run in batch], pieces)
    return counts


def _replace(
    lake: Lakehouse, name: str, column: str, ids: list[str], pieces: Callable[[set[str]], Iterator[pa.Table]]
) -> None:
    """One commit on table `name`: rows whose `column` is one of `ids` deleted, then `pieces` (given
    the table's columns, made again for each attempt) appended; a commit lost to another writer is
    made again on the table as that writer left it. A delete that matches no row adds nothing to
    the transaction, and the append is made only with files: with neither, nothing is committed."""
    for attempt in range(COMMIT_ATTEMPTS):
        table = lake.table(name)
        try:
            with table.transaction() as tx, warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "Delete operation did not match any records": a new run
                tx.delete(In(column, ids))  # type: ignore[call-arg,arg-type]  # pydantic model: mypy misreads it
                written = [
                    data_file
                    for piece in pieces(set(tx.table_metadata.schema().column_names))
                    for data_file in _dataframe_to_data_files(
                        table_metadata=tx.table_metadata,
                        write_uuid=uuid.uuid4(),  # names its files: one per piece, never reused
                        df=piece,
                        io=table.io,
                    )
                ]
                if written:
                    with tx.update_snapshot().merge_append() as append:
                        for data_file in written:
                            append.append_data_file(data_file)
            return
        except (CommitFailedException, ValidationException) as exc:
            if attempt == COMMIT_ATTEMPTS - 1:
                raise
            log.info("lakehouse %s: commit lost to another writer (%s), trying again", name, exc)
            time.sleep(0.05 * 2**attempt)


def _add_columns(lake: Lakehouse, name: str, sources: list[_Source]) -> None:
    """Timelines the batch brings that the table has no column for yet become columns (up to
    MAX_COLUMNS), committed before the rows so the data commit never races a schema change."""
    table = lake.table(name)
    held = set(table.schema().column_names)
    wanted: dict[str, pa.Field] = {}
    for source in sources:
        run = source.run
        assert run.robot_id is not None and run.date is not None
        empty = pa.RecordBatch.from_pylist([], schema=source.metadata.schema.to_arrow_schema())
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
