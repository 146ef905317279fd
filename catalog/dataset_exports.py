"""Catalog reads and writes of dataset export jobs (`dataset_exports`): one added queued, claimed by a
depot process with a heartbeat (a claim is one conditional UPDATE, so two processes never run the
same job), its progress written as it goes, and its end (done, failed, cancelled).

A running job whose heartbeat is older than the stale bound is due again: its process died, and the
next one resumes it after its last written episode.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.models import DatasetExport

QUEUED, RUNNING, DONE, FAILED, CANCELLED = "queued", "running", "done", "failed", "cancelled"
FINAL = frozenset({DONE, FAILED, CANCELLED})


def add(session: Session, row: DatasetExport) -> DatasetExport:
    session.add(row)
    session.flush()
    return row


def get(session: Session, job_id: str) -> DatasetExport | None:
    return session.get(DatasetExport, job_id)


def listed(session: Session, name: str | None, version: int | None, limit: int) -> list[DatasetExport]:
    """Jobs newest first, of one snapshot (and version) if given."""
    query = sa.select(DatasetExport).order_by(DatasetExport.created_at.desc(), DatasetExport.id.desc()).limit(limit)
    if name is not None:
        query = query.where(DatasetExport.name == name)
    if version is not None:
        query = query.where(DatasetExport.version == version)
    return list(session.scalars(query))


def due(session: Session, stale_before: dt.datetime) -> list[str]:
    """Jobs to run, oldest first: queued, or running with a heartbeat older than `stale_before`."""
    query = (
        sa.select(DatasetExport.id)
        .where(
            sa.or_(
                DatasetExport.state == QUEUED,
                sa.and_(DatasetExport.state == RUNNING, DatasetExport.heartbeat_at < stale_before),
            )
        )
        .order_by(DatasetExport.created_at, DatasetExport.id)
    )
    return list(session.scalars(query))


def claim(session: Session, job_id: str, node: str, now: dt.datetime, stale_before: dt.datetime) -> bool:
    """Take the job for `node` if it is still due; whether it was taken."""
    taken = session.execute(
        sa.update(DatasetExport)
        .where(
            DatasetExport.id == job_id,
            sa.or_(
                DatasetExport.state == QUEUED,
                sa.and_(DatasetExport.state == RUNNING, DatasetExport.heartbeat_at < stale_before),
            ),
        )
        .values(state=RUNNING, node=node, heartbeat_at=now, updated_at=now)
        .returning(DatasetExport.id)
        .execution_options(synchronize_session=False)
    )
    return taken.first() is not None


@dataclass(frozen=True)
class Progress:
    done: int
    frames: int
    skipped: int
    flagged: int
    bytes: int
    report: str  # JSON


def beat(session: Session, job_id: str, node: str, now: dt.datetime, progress: Progress | None = None) -> str | None:
    """The heartbeat (and progress) of a job `node` runs; the job's state, None if another took it."""
    values: dict[str, object] = {"heartbeat_at": now, "updated_at": now}
    if progress is not None:
        values.update(
            done=progress.done,
            frames=progress.frames,
            skipped=progress.skipped,
            flagged=progress.flagged,
            bytes=progress.bytes,
            report=progress.report,
        )
    session.execute(
        sa.update(DatasetExport)
        .where(DatasetExport.id == job_id, DatasetExport.node == node, DatasetExport.state == RUNNING)
        .values(**values)
    )
    row = session.get(DatasetExport, job_id, populate_existing=True)
    if row is None or row.node != node:
        return None
    return row.state


def end(session: Session, job_id: str, node: str, state: str, now: dt.datetime, error: str | None = None) -> None:
    """The job ends (done or failed) if `node` still runs it; a cancel stands."""
    session.execute(
        sa.update(DatasetExport)
        .where(DatasetExport.id == job_id, DatasetExport.node == node, DatasetExport.state == RUNNING)
        .values(state=state, error=error, updated_at=now, heartbeat_at=now)
    )


def cancel(session: Session, job_id: str, now: dt.datetime) -> bool:
    """Cancel a job not yet ended; whether it was."""
    taken = session.execute(
        sa.update(DatasetExport)
        .where(DatasetExport.id == job_id, DatasetExport.state.in_([QUEUED, RUNNING]))
        .values(state=CANCELLED, updated_at=now)
        .returning(DatasetExport.id)
        .execution_options(synchronize_session=False)
    )
    return taken.first() is not None
