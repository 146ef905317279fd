"""The catalog's side of the lakehouse: which runs its Iceberg tables must copy again.

A writer that changes what the tables hold of a run (its analytics files, its catalog row's tier,
its metrics, events or tags, its deletion) calls `queue` in its own transaction, so a committed
change is never missed; the sync job reads `pending`, copies each run, and `done` clears the mark
only if no change came meanwhile (the run stays pending otherwise).
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa
from sqlalchemy.dialects.postgresql import insert
from sqlalchemy.orm import Session

from catalog.models import LakehouseRun, Run, RunObject
from core.states import Tier

ANALYTICS = "analytics/"  # the name prefix of a run's analytics objects (`analytics/TABLE`)


@dataclass(frozen=True)
class PendingRun:
    """A run the tables must copy again: its files now (none once it is deleted or gone)."""

    run_id: str
    wanted: int
    telemetry: bool  # its analytics files changed: their rows are copied again
    robot_id: str | None
    date: dt.date | None
    files: dict[str, str]  # table -> warm key of its Parquet file

    @property
    def gone(self) -> bool:
        return self.robot_id is None


def queue(session: Session, run_id: str, telemetry: bool = False) -> None:
    """Mark the run's rows for copying again, in the caller's transaction (`telemetry`: its analytics
    files' rows too)."""
    statement = insert(LakehouseRun).values(
        run_id=run_id, wanted=1, synced=0, pending=True, telemetry=telemetry, rows=0
    )
    changes: dict[str, Any] = {"wanted": LakehouseRun.wanted + 1, "pending": True}
    if telemetry:
        changes["telemetry"] = True
    session.execute(statement.on_conflict_do_update(index_elements=["run_id"], set_=changes))


def queue_sealed(session: Session, run_ids: list[str]) -> None:
    """Mark those of the runs that are sealed (their metrics, events or tags changed): a hot run's
    catalog rows reach the tables when it is sealed, not each time the live rules write it."""
    if not run_ids:
        return
    for run_id in session.scalars(sa.select(Run.id).where(Run.id.in_(run_ids), Run.tier != Tier.HOT).order_by(Run.id)):
        queue(session, run_id)


def queue_all(session: Session) -> int:
    """Mark every run with analytics files that the tables do not hold yet (what `fleet analytics
    migrate` starts with); returns how many were marked."""
    held = sa.select(LakehouseRun.run_id)
    runs = session.scalars(
        sa.select(RunObject.run_id)
        .join(Run, Run.id == RunObject.run_id)
        .where(RunObject.name.like(f"{ANALYTICS}%"), Run.tier != Tier.DELETED, RunObject.run_id.not_in(held))
        .distinct()
        .order_by(RunObject.run_id)
    ).all()
    for run_id in runs:
        queue(session, run_id, telemetry=True)
    return len(runs)


def pending(session: Session, limit: int, only: list[str] | None = None) -> list[PendingRun]:
    """Up to `limit` runs to copy (of `only`, if given), in id order, with their files as the catalog
    lists them now."""
    query = sa.select(LakehouseRun.run_id, LakehouseRun.wanted, LakehouseRun.telemetry).where(
        LakehouseRun.pending.is_(True)
    )
    if only is not None:
        query = query.where(LakehouseRun.run_id.in_(only))
    marked = session.execute(query.order_by(LakehouseRun.run_id).limit(limit)).all()
    ids = [row[0] for row in marked]
    runs = {run.id: run for run in session.scalars(sa.select(Run).where(Run.id.in_(ids), Run.tier != Tier.DELETED))}
    files: dict[str, dict[str, str]] = {}
    for run_id, name, key in session.execute(
        sa.select(RunObject.run_id, RunObject.name, RunObject.key).where(
            RunObject.run_id.in_(list(runs)), RunObject.name.like(f"{ANALYTICS}%")
        )
    ):
        files.setdefault(run_id, {})[name.removeprefix(ANALYTICS)] = key
    out = []
    for run_id, wanted, telemetry in marked:
        run = runs.get(run_id)
        if run is None:
            out.append(PendingRun(run_id, wanted, telemetry, None, None, {}))
        else:
            out.append(PendingRun(run_id, wanted, telemetry, run.robot_id, run.date, files.get(run_id, {})))
    return out


def done(session: Session, run_id: str, wanted: int, rows: int | None, now: dt.datetime) -> bool:
    """The tables hold change `wanted` of the run (`rows`: its telemetry rows, if they were copied);
    False if another change came since (still pending)."""
    changed = session.execute(
        sa.update(LakehouseRun)
        .where(LakehouseRun.run_id == run_id, LakehouseRun.wanted == wanted)
        .values(
            synced=wanted,
            pending=False,
            telemetry=False,
            synced_at=now,
            rows=LakehouseRun.rows if rows is None else rows,
        )
        .execution_options(synchronize_session=False)
    )
    return bool(getattr(changed, "rowcount", 0))


def pending_count(session: Session) -> int:
    return int(session.scalar(sa.select(sa.func.count()).where(LakehouseRun.pending.is_(True))) or 0)
