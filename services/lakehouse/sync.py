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
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from sqlalchemy.orm import Session, sessionmaker

from catalog import lakehouse as marks
from catalog.db import session_scope
from services.storage.objectstore import ObjectStore

if TYPE_CHECKING:
    from services.lakehouse.tables import Lakehouse

log = logging.getLogger(__name__)

JOB = "lakehouse.sync"
BATCH_RUNS = 32  # runs per commit: fewer commits (and snapshots) than one per run, bounded work
JOB_BATCHES = 16  # batches one pass of the job copies at most: the rest wait for the next pass


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
        # here: pyiceberg takes a third of a second to import, which a depot that never writes
        # the tables (or not yet) does not pay at start-up
        from services.lakehouse.writes import copy_batch

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
