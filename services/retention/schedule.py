"""The one place retention jobs are registered and scheduled (APScheduler, inside `fleet serve`).

- `promote`: this node's closed hot runs into the warm tier (every node promotes its own runs;
  one promotion at a time per process).
- `retention`: archive, restores and deletion over the whole catalog: one process at a time
  across every service process on the catalog (a Postgres advisory lock), others skip that turn.
- `ownership`: with many nodes on one catalog, this node's hot runs matched with their leases, and
  copies of runs other nodes own handed to them (`handoff.py`); not recorded in `job_runs` (it runs
  every few seconds).
Each job run is recorded in the catalog (`job_runs`): where, when, and how it went.

Jobs of sides above retention (the webhooks' delivery and `robot.silent` passes, the rules
backfill of `services.corpus.backfill`) are given to
`start_scheduler` by the wiring (`services/server.py`) as `extra` jobs, and run here alike.
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import socket
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from apscheduler.schedulers.background import BackgroundScheduler

from catalog import queries
from catalog.db import session_scope
from services.retention.handoff import ownership_pass
from services.retention.locks import job_lock
from services.retention.promote import PROMOTING
from services.retention.service import (
    ARCHIVE,
    DELETE,
    PROMOTE,
    RESTORE,
    Outcome,
    Retention,
    catalog_engine,
    plan,
    run_plan,
)

log = logging.getLogger(__name__)

Progress = Callable[[Outcome], None] | None


def node_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def promote_job(ctx: Retention, progress: Progress = None, *, wait: bool = False) -> list[Outcome] | None:
    """Promote this node's due hot runs; None if a promotion pass is already running here."""
    if not PROMOTING.acquire(blocking=wait):
        return None
    try:
        actions = plan(ctx, [PROMOTE])
        return _recorded(ctx, "promote", lambda: run_plan(ctx, actions, progress)) if actions else []
    finally:
        PROMOTING.release()


def retention_job(
    ctx: Retention, progress: Progress = None, kinds: tuple[str, ...] = (ARCHIVE, DELETE, RESTORE)
) -> list[Outcome] | None:
    """Archive, advance restores and delete what is due; None if another process runs it now."""
    with job_lock(catalog_engine(ctx), "retention") as got:
        if not got:
            log.info("retention job is running in another process: skipped")
            return None
        return _recorded(ctx, "retention", lambda: run_plan(ctx, plan(ctx, kinds), progress))


def run_now(ctx: Retention, kinds: list[str], emit: Callable[[dict[str, Any]], None]) -> None:
    """`POST /v1/retention/run`: do what is due now through the jobs (so nothing runs twice at once),
    saying so as it goes: the plan, one line per run done, and the sums at the end."""
    actions = plan(ctx, kinds)
    emit({"event": "plan", "total": len(actions), "actions": [a.to_dict() for a in actions]})
    promotions = [a for a in actions if a.action == PROMOTE]
    others = [a for a in actions if a.action != PROMOTE]
    done = []

    def progress(outcome: Outcome) -> None:
        done.append(outcome)
        emit({"event": "done", **outcome.to_dict()})

    if promotions:
        promote_job(ctx, progress, wait=True)
    catalog_kinds = tuple(k for k in kinds if k in (ARCHIVE, DELETE, RESTORE))
    if others and retention_job(ctx, progress, catalog_kinds) is None:
        emit({"event": "busy", "detail": "the retention job is running in another process; try again"})
    emit({"event": "end", "done": sum(o.ok for o in done), "failed": sum(not o.ok for o in done)})


JOB_HISTORY = dt.timedelta(days=30)  # job runs kept in the catalog (GET /v1/retention shows the newest)


def _recorded(ctx: Retention, job: str, body: Callable[[], list[Outcome]]) -> list[Outcome]:
    with session_scope(ctx.catalog, write=True) as session:
        queries.prune_jobs(session, ctx.clock() - JOB_HISTORY)
        job_id = queries.start_job(session, job, node_name(), ctx.clock())
    outcomes: list[Outcome] = []
    try:
        outcomes = body()
    except Exception as exc:
        with session_scope(ctx.catalog, write=True) as session:
            queries.finish_job(session, job_id, ctx.clock(), "failed", f"{type(exc).__name__}: {exc}")
        raise
    failed = [o for o in outcomes if not o.ok]
    summary = f"{len(outcomes) - len(failed)} done, {len(failed)} failed" + "".join(
        f"; {o.action.action} {o.action.run_id}: {o.detail}" for o in failed[:5]
    )
    with session_scope(ctx.catalog, write=True) as session:
        queries.finish_job(session, job_id, ctx.clock(), "failed" if failed else "ok", summary)
    return outcomes


@dataclass(frozen=True)
class Job:
    name: str
    run: Callable[[Retention], object]
    interval_s: float


def ownership_job(ctx: Retention) -> None:
    if ctx.ingest is not None:
        ownership_pass(ctx.ingest, ctx.node)


def jobs(
    promote_interval_s: float,
    retention_interval_s: float,
    lease_s: float | None = None,
    extra: Sequence[Job] = (),
) -> list[Job]:
    found = [Job("promote", promote_job, promote_interval_s), Job("retention", retention_job, retention_interval_s)]
    if lease_s is not None:  # many nodes on one catalog
        found.append(Job("ownership", ownership_job, max(0.5, lease_s / 2)))
    return [*found, *extra]


def start_scheduler(
    ctx: Retention,
    promote_interval_s: float,
    retention_interval_s: float,
    lease_s: float | None = None,
    extra: Sequence[Job] = (),
) -> BackgroundScheduler:
    """The jobs above, and `extra` jobs of other sides (each given `ctx`, which it may ignore)."""
    scheduler = BackgroundScheduler(timezone="UTC")
    for job in jobs(promote_interval_s, retention_interval_s, lease_s, extra):
        scheduler.add_job(
            _guarded(job, ctx),
            "interval",
            seconds=job.interval_s,
            id=job.name,
            name=job.name,
            max_instances=1,
            coalesce=True,
        )
    scheduler.start()
    return scheduler


def _guarded(job: Job, ctx: Retention) -> Callable[[], None]:
    def run() -> None:
        try:
            job.run(ctx)
        except Exception:  # logged; the next interval retries
            log.exception("%s job failed", job.name)

    return run
