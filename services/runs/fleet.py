"""The fleet at a glance, as plain values: robots and their last runs, runs per robot per day, data
by tier, object-store and hot-disk usage, recent retention jobs and events, and the runs live now.

What the catalog says is read in one session; what only this node knows (its hot disk, the hot runs
it is writing, fresher than their catalog rows) comes from ingest's read-only view."""

from __future__ import annotations

import datetime as dt
import shutil
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import InstrumentedAttribute, Session, aliased

from catalog.db import is_embedded, session_scope
from catalog.models import JobExecution, RetentionEvent, Robot, Run
from core.clock import aware, iso_utc, utcnow
from core.states import RunStatus, Tier
from services.hot.store import HotStore
from services.ingest.service import IngestService
from services.ingest.view import HotRunView
from services.node import Node
from services.runs import totals
from services.runs.service import run_summary

DAYS = 14  # runs per robot per day: this many days, today included
RECENT = 10  # retention jobs and events shown
FAILURES = 5  # failed jobs shown even when older than the recent ones
LIVE_LIMIT = 50  # live runs listed


def _started() -> sa.ColumnElement[dt.datetime]:
    return sa.func.coalesce(Run.started_at, Run.created_at)


def _newest_run_of(robot_id: sa.ColumnElement[str] | InstrumentedAttribute[str]) -> sa.ScalarSelect[str]:
    """The id of the robot's last run by start (deleted runs left out): one index probe per robot
    on Postgres (`ix_runs_robot_started`), where ranking every run would read them all."""
    run = aliased(Run, name="newest")
    started = sa.func.coalesce(run.started_at, run.created_at)
    query = sa.select(run.id).where(run.robot_id == robot_id, run.tier != Tier.DELETED)
    return query.order_by(started.desc(), run.id.desc()).limit(1).correlate_except(run).scalar_subquery()


def _ranked_last_runs(session: Session) -> dict[str, Run]:
    """Each robot's last run (by start), by ranking every run: what the embedded catalog does fast
    (a scan of its columns), where a probe per robot costs it a scan each."""
    started = _started()
    ranked = (
        sa.select(
            Run.id.label("run_id"),
            sa.func.row_number().over(partition_by=Run.robot_id, order_by=(started.desc(), Run.id.desc())).label("n"),
        )
        .where(Run.tier != Tier.DELETED)
        .subquery()
    )
    newest = sa.select(Run).join(ranked, ranked.c.run_id == Run.id).where(ranked.c.n == 1)
    return {run.robot_id: run for run in session.scalars(newest)}


def last_runs(session: Session, unlisted: list[str]) -> dict[str, Run]:
    """Each robot's last run (by start): the robots the catalog has a row of, and `unlisted`, robot
    ids of runs whose robot has none."""
    if is_embedded(session.get_bind().engine):
        return _ranked_last_runs(session)
    with_row = sa.select(Run).join(Robot, Run.id == _newest_run_of(Robot.id))
    last = {run.robot_id: run for run in session.scalars(with_row)}
    if unlisted:
        ids = sa.values(sa.column("robot_id", sa.String), name="unlisted").data([(r,) for r in unlisted])
        others = sa.select(Run).join(ids, Run.id == _newest_run_of(ids.c.robot_id))
        last.update({run.robot_id: run for run in session.scalars(others)})
    return last


def robots(session: Session, counts: dict[str, int]) -> list[dict[str, Any]]:
    """Every robot with its run count (deleted runs not counted: `counts`, as `totals` has them) and
    its last run (by start)."""
    seen: dict[str, Robot | None] = {robot.id: robot for robot in session.scalars(sa.select(Robot))}
    last = last_runs(session, sorted(set(counts) - set(seen)))
    for robot_id in counts:
        seen.setdefault(robot_id, None)
    out = []
    for robot_id in sorted(seen):
        robot = seen[robot_id]
        run = last.get(robot_id)
        out.append(
            {
                "id": robot_id,
                "runs": counts.get(robot_id, 0),
                "last_seen_at": iso_utc(robot.last_seen_at) if robot is not None else None,
                "last_run": run_summary(run) if run is not None else None,
            }
        )
    return out


def runs_per_day(session: Session, today: dt.date, days: int = DAYS) -> dict[str, Any]:
    """How many runs each robot started on each of the last `days` days (UTC dates, oldest first;
    deleted runs not counted)."""
    first = today - dt.timedelta(days=days - 1)
    dates = [first + dt.timedelta(days=i) for i in range(days)]
    rows = session.execute(
        sa.select(Run.robot_id, Run.date, sa.func.count())
        .where(Run.date >= first, Run.date <= today, Run.tier != Tier.DELETED)
        .group_by(Run.robot_id, Run.date)
    ).all()
    counts: dict[str, list[int]] = {}
    for robot_id, day, n in rows:
        day = day.date() if isinstance(day, dt.datetime) else day
        counts.setdefault(robot_id, [0] * days)[(day - first).days] = int(n)
    totals = [sum(c[i] for c in counts.values()) for i in range(days)]
    return {
        "days": [d.isoformat() for d in dates],
        "robots": [{"id": r, "counts": counts[r], "total": sum(counts[r])} for r in sorted(counts)],
        "totals": totals,
        "max": max((n for c in counts.values() for n in c), default=0),
    }


def _job(job: JobExecution) -> dict[str, Any]:
    finished = job.finished_at
    took = (aware(finished) - aware(job.started_at)).total_seconds() if finished is not None else None
    return {
        "id": job.id,
        "job": job.job,
        "node": job.node,
        "started_at": iso_utc(job.started_at),
        "finished_at": iso_utc(finished),
        "seconds": took,
        "outcome": job.outcome,
        "failed": job.outcome == "failed",
        "detail": job.detail,
    }


def recent_jobs(session: Session, limit: int = RECENT) -> list[dict[str, Any]]:
    """The latest scheduled job runs (promote, retention), newest first."""
    query = sa.select(JobExecution).order_by(JobExecution.started_at.desc(), JobExecution.id.desc()).limit(limit)
    return [_job(job) for job in session.scalars(query)]


def failed_jobs(session: Session, limit: int = FAILURES) -> list[dict[str, Any]]:
    """The latest job runs that failed (the catalog keeps a month of them), newest first."""
    query = (
        sa.select(JobExecution)
        .where(JobExecution.outcome == "failed")
        .order_by(JobExecution.started_at.desc(), JobExecution.id.desc())
        .limit(limit)
    )
    return [_job(job) for job in session.scalars(query)]


def recent_events(session: Session, limit: int = RECENT) -> list[dict[str, Any]]:
    """What retention (or a person) did to runs lately: promote, archive, restore, pin, delete..."""
    query = sa.select(RetentionEvent).order_by(RetentionEvent.occurred_at.desc(), RetentionEvent.id.desc()).limit(limit)
    return [
        {
            "run_id": e.run_id,
            "action": e.action,
            "at": iso_utc(e.occurred_at),
            "actor": e.actor,
            "policy": e.policy,
            "detail": e.detail,
        }
        for e in session.scalars(query)
    ]


def live_in_catalog(session: Session, limit: int = LIVE_LIMIT) -> list[dict[str, Any]]:
    """Runs a stream still feeds, on any node (their catalog rows), latest data first."""
    query = (
        sa.select(Run)
        .where(Run.status == RunStatus.LIVE, Run.tier != Tier.DELETED)
        .order_by(Run.last_data_at.desc(), Run.id)
        .limit(limit)
    )
    return [{**run_summary(run), "here": False} for run in session.scalars(query)]


def _hot_brief(run: HotRunView, default_robot: str) -> dict[str, Any]:
    start_ns = run.started_ns
    started = dt.datetime.fromtimestamp(start_ns / 1e9, dt.UTC) if start_ns else None
    return {
        "id": run.run_id,
        "robot_id": run.robot_id or default_robot,
        "application_id": run.application_id,
        "status": str(run.status),
        "tier": str(Tier.HOT),
        "started_at": iso_utc(started),
        "ended_at": iso_utc(run.ended_at),
        "last_data_at": iso_utc(run.last_data_at),
        "bytes": run.size,
        "chunks": run.chunks,
        "here": True,
    }


def hot_here(ingest: IngestService | None, default_robot: str) -> list[dict[str, Any]]:
    """The hot runs this node holds (being written, or closed and waiting to be sealed), newest
    data first, as ingest knows them now."""
    if ingest is None:
        return []
    runs = [_hot_brief(run, default_robot) for run in ingest.hot_runs()]
    return sorted(runs, key=lambda r: (r["last_data_at"] or "", r["id"]), reverse=True)


def live_now(catalog_live: list[dict[str, Any]], hot: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Runs live now (any node), and this node's hot runs (what it knows of them is fresher than
    their rows), newest data first."""
    merged = {run["id"]: run for run in catalog_live}
    merged.update({run["id"]: run for run in hot})
    return sorted(merged.values(), key=lambda r: (r["last_data_at"] or "", r["id"]), reverse=True)[:LIVE_LIMIT]


def disk_usage(root: Path, reserve: int = 0) -> dict[str, Any]:
    """The file system holding `root`: its size, used and free bytes, and the reserve the hot tier
    keeps free (ingest refuses data below it)."""
    usage = shutil.disk_usage(root)
    return {
        "path": str(root),
        "total": usage.total,
        "used": usage.used,
        "free": usage.free,
        "used_fraction": usage.used / usage.total if usage.total else 0.0,
        "reserve": reserve,
    }


def hot_disk(store: HotStore | None, hot: list[dict[str, Any]]) -> dict[str, Any] | None:
    """This node's hot disk, with the hot runs on it; None on a node that ingests nothing."""
    if store is None:
        return None
    try:
        usage = disk_usage(store.root, store.min_free_bytes)
    except OSError as exc:  # the disk went away: shown as such, the rest of the overview still answers
        return {"path": str(store.root), "problem": f"cannot read the hot tier's disk: {exc.strerror or exc}"}
    return {
        **usage,
        "runs": len(hot),
        "live": sum(r["status"] == RunStatus.LIVE for r in hot),
        "run_bytes": sum(int(r["bytes"]) for r in hot),
        "problem": None,
    }


def overview(node: Node, ingest: IngestService | None, *, now: dt.datetime | None = None) -> dict[str, Any]:
    """The fleet overview: everything the console's first page shows, as plain values (this node's
    hot runs and disk from `ingest`, when it has one)."""
    now = now or utcnow()
    with session_scope(node.catalog) as session:
        counted = totals.totals(session, now)
        answer: dict[str, Any] = {
            "robots": robots(session, counted.robots),
            "per_day": runs_per_day(session, now.astimezone(dt.UTC).date()),
            "tiers": counted.tiers,
            "objects": counted.objects,
            "totals_counted_at": counted.counted_at,  # None: counted for this answer
            "jobs": recent_jobs(session),
            "failures": failed_jobs(session),
            "events": recent_events(session),
        }
        catalog_live = live_in_catalog(session)
    hot = hot_here(ingest, node.default_robot)
    answer["live"] = live_now(catalog_live, hot)
    answer["hot_disk"] = hot_disk(node.hot if ingest is not None else None, hot)
    answer["generated_at"] = iso_utc(now)
    return answer
