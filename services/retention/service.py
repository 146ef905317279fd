"""Retention: what should move or go, and doing it; pins and restores asked for by users.

`plan()` lists actions with their reasons (what `fleet retention plan` prints); `execute()` does
one. The scheduled jobs (`services.retention.schedule`) are these two over a subset of actions.
"""

from __future__ import annotations

import datetime as dt
import logging
import shutil
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from catalog import datasets, queries
from catalog.db import session_scope
from catalog.models import Run
from core.clock import aware, iso_utc
from core.errors import ConflictError
from core.states import ARCHIVED_IN_STORE, RestoreState, RunStatus, Tier
from services.ingest.service import IngestService
from services.lakehouse.sync import copy_now
from services.node import Node
from services.policies import Policies, Policy
from services.retention import archive, promote
from services.sealed.tiers import Tiers, write_run_json
from services.settings import Settings

log = logging.getLogger(__name__)

PROMOTE, ARCHIVE, DELETE, RESTORE = "promote", "archive", "delete", "restore"
ACTIONS = (PROMOTE, ARCHIVE, DELETE, RESTORE)
KEEP = "keep"  # a run past its policy's deletion kept (pinned, or used by a dataset snapshot): the plan says why


@dataclass
class Retention:
    """What the retention jobs work with beside the node, built once by the server (or a test)."""

    node: Node
    policies: Policies
    ingest: IngestService | None = None  # promotion needs this node's hot runs
    promote_after: dt.timedelta = dt.timedelta(minutes=10)
    promote_below_free_bytes: int = 0
    restore_days: float = 7.0
    free_bytes: Callable[[], int] | None = None  # of the hot disk (default: asked of the file system)
    reserve_bytes: int = 0  # promotion never takes the hot disk below this much free
    promote_backoff: promote.PromoteBackoff = field(default_factory=promote.PromoteBackoff)  # failed promotions
    on_sealed: promote.OnSealed | None = None  # told each run sealed here (the server wires the corpus)

    # The node's, named here as the jobs have always named them.
    @property
    def catalog(self) -> sessionmaker[Session]:
        return self.node.catalog

    @property
    def tiers(self) -> Tiers:
        return self.node.tiers

    @property
    def clock(self) -> Callable[[], dt.datetime]:
        return self.node.clock

    def hot_free_bytes(self) -> int:
        if self.free_bytes is not None:
            return self.free_bytes()
        return shutil.disk_usage(self.node.hot.root).free


def catalog_engine(ctx: Retention) -> sa.Engine:
    """The engine under the catalog's sessions: the jobs' locks are held on connections of it."""
    bind = ctx.catalog.kw["bind"]
    assert isinstance(bind, sa.Engine)
    return bind


@dataclass(frozen=True)
class Action:
    run_id: str
    action: str  # promote | archive | delete | restore
    reason: str
    robot_id: str = ""
    tier: str = ""
    bytes: int = 0
    policy: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "run": self.run_id,
            "action": self.action,
            "reason": self.reason,
            "robot_id": self.robot_id,
            "tier": self.tier,
            "bytes": self.bytes,
            "policy": self.policy,
        }


@dataclass
class Outcome:
    action: Action
    ok: bool
    detail: str
    seconds: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {**self.action.to_dict(), "ok": self.ok, "detail": self.detail, "seconds": round(self.seconds, 3)}


def _days(delta: dt.timedelta) -> str:
    return f"{delta.total_seconds() / 86400:.1f} days"


def overview(ctx: Retention, settings: Settings) -> dict[str, Any]:
    """`GET /v1/retention`: the policies and settings retention works with, and its recent job runs."""
    with session_scope(ctx.catalog) as session:
        jobs = [
            {
                "job": j.job,
                "node": j.node,
                "started_at": aware(j.started_at).isoformat(),
                "finished_at": aware(j.finished_at).isoformat() if j.finished_at else None,
                "outcome": j.outcome,
                "detail": j.detail,
            }
            for j in queries.recent_jobs(session)
        ]
    return {
        "policies": ctx.policies.to_dict(),
        "promote_after_s": ctx.promote_after.total_seconds(),
        "promote_below_free_bytes": ctx.promote_below_free_bytes,
        "restore_days": ctx.restore_days,
        "archive": ctx.tiers.archive_mode(),
        "warm_url": ctx.tiers.warm.url,
        "cold_url": ctx.tiers.cold.url,
        "schedule": {
            "enabled": settings.scheduler,
            "promote_interval_s": settings.promote_interval_s,
            "retention_interval_s": settings.retention_interval_s,
        },
        "recent_jobs": jobs,
    }


def plan_answer(ctx: Retention, kinds: list[str]) -> dict[str, Any]:
    """`GET /v1/retention/plan`: what is due now and why, (with promotions asked for) the hot runs
    that are not due yet, and (with deletions asked for) the runs past their policy that are kept,
    each with why (pinned, used by a dataset snapshot)."""
    coming = upcoming(ctx) if PROMOTE in kinds else []
    actions, kept = _planned(ctx, kinds)
    return {"actions": [a.to_dict() for a in actions], "upcoming": coming, "kept": [k.to_dict() for k in kept]}


def plan(ctx: Retention, kinds: Iterable[str] = ACTIONS) -> list[Action]:
    """What is due now, and why (oldest first within each kind)."""
    return _planned(ctx, kinds)[0]


def _planned(ctx: Retention, kinds: Iterable[str]) -> tuple[list[Action], list[Action]]:
    """What is due now, and the runs past their policy's deletion that are kept (with why)."""
    kinds = set(kinds)
    now = ctx.clock()
    actions: list[Action] = []
    kept: list[Action] = []
    if PROMOTE in kinds and ctx.ingest is not None:
        pressure = ctx.promote_below_free_bytes > 0 and ctx.hot_free_bytes() < ctx.promote_below_free_bytes
        for cand in promote.due_for_promotion(
            ctx.ingest, ctx.node, now, ctx.promote_after, pressure, ctx.promote_backoff
        ):
            record = cand.run.record(ctx.node.default_robot)
            actions.append(Action(cand.run.run_id, PROMOTE, cand.reason, record.robot_id, Tier.HOT, record.bytes))
    if kinds & {ARCHIVE, DELETE, RESTORE}:
        with session_scope(ctx.catalog) as session:
            sealed = queries.sealed_runs(session, (Tier.WARM, Tier.COLD), may_be_due(ctx.policies, now))
            expired = [run.id for run, _ in sealed if _expired(ctx, run, now)] if DELETE in kinds else []
            used = datasets.snapshots_using(session, expired)  # asked only of the runs it could matter to
            for run, life in sealed:
                action = _due(ctx, run, life, now, kinds, used)
                if action is not None:
                    actions.append(action)
                if run.id in expired and (run.pinned or run.id in used):
                    kept.append(_kept(ctx, run, used.get(run.id, [])))
    return actions, kept


def may_be_due(policies: Policies, now: dt.datetime) -> sa.ColumnElement[bool]:
    """A condition on a sealed run that holds for every run the plan can archive or delete, or
    keep past its deletion: warm past its policy's archive age, or past its deletion age. Each
    policy's runs are named as `Policies.for_run` chooses (an override for the robot, else one for
    the application, else the default). Every arm names the tiers it is about, so that Postgres
    reads each from `ix_runs_tier_end` (tier, end) rather than every run of a robot or application."""
    robots = sorted({o.robot for o in policies.overrides if o.robot is not None})
    applications = sorted({o.application for o in policies.overrides if o.application is not None})
    outsider = "\x00"  # a robot id no override names (no run's robot id holds a NUL)
    others = [Run.robot_id.not_in(robots)] if robots else []
    governed = [(Run.robot_id == robot, policies.for_run(robot, "")) for robot in robots]
    governed += [
        (sa.and_(Run.application_id == application, *others), policies.for_run(outsider, application))
        for application in applications
    ]
    unnamed = [*others, *([Run.application_id.not_in(applications)] if applications else [])]
    governed.append((sa.and_(sa.true(), *unnamed), policies.default))
    return sa.or_(*(sa.and_(runs, past) for runs, policy in governed for past in _past_age(policy, now)))


def _past_age(policy: Policy, now: dt.datetime) -> list[sa.ColumnElement[bool]]:
    """Sealed past `policy`'s deletion age; warm past its archive age (when it archives at all)."""
    end = queries.run_end()
    deletion = sa.and_(Run.tier.in_((Tier.WARM, Tier.COLD)), end <= now - policy.delete_after)
    if policy.cold_days <= 0:
        return [deletion]
    return [deletion, sa.and_(Run.tier == Tier.WARM, end <= now - policy.archive_after)]


def _expired(ctx: Retention, run: Any, now: dt.datetime) -> bool:
    """Past its policy's deletion age (whether or not it is kept)."""
    policy = ctx.policies.for_run(run.robot_id, run.application_id)
    return now - aware(run.ended_at or run.last_data_at) >= policy.delete_after


def _kept(ctx: Retention, run: Any, used: list[str]) -> Action:
    """Why a run past its policy's deletion stays: pinned (by whom), used by dataset snapshots."""
    policy = ctx.policies.for_run(run.robot_id, run.application_id)
    why = ([f"pinned by {run.pinned_by or 'someone'}"] if run.pinned else []) + (
        [f"used by {datasets.describe_use(used)}"] if used else []
    )
    return Action(run.id, KEEP, "; ".join(why), run.robot_id, run.tier, run.bytes, policy.name)


def _due(
    ctx: Retention, run: Any, life: Any, now: dt.datetime, kinds: set[str], used: dict[str, list[str]]
) -> Action | None:
    policy = ctx.policies.for_run(run.robot_id, run.application_id)
    age = now - aware(run.ended_at or run.last_data_at)
    common = {"robot_id": run.robot_id, "tier": run.tier, "bytes": run.bytes, "policy": policy.name}
    if age >= policy.delete_after and DELETE in kinds and not run.pinned and run.id not in used:
        return Action(
            run.id,
            DELETE,
            f"ended {_days(age)} ago; policy {policy.name!r} keeps runs "
            f"{policy.warm_days:g} days warm + {policy.cold_days:g} days cold",
            **common,
        )
    if life.restore_state is not None and RESTORE in kinds:
        until = aware(life.restore_until) if life.restore_until else None
        if life.restore_state == RestoreState.RESTORING or (until is not None and until <= now):
            why = "restore asked for" if life.restore_state == RestoreState.RESTORING else "restore period is over"
            return Action(run.id, RESTORE, why, **common)
    if run.tier == Tier.WARM and age >= policy.archive_after and policy.cold_days > 0 and ARCHIVE in kinds:
        return Action(
            run.id,
            ARCHIVE,
            f"ended {_days(age)} ago; policy {policy.name!r} keeps runs {policy.warm_days:g} days warm",
            **common,
        )
    return None


def execute(ctx: Retention, action: Action) -> Outcome:
    """Do one planned action; failures are reported, not raised (the next run retries)."""
    start = dt.datetime.now(dt.UTC)
    now = ctx.clock()
    try:
        detail = _execute(ctx, action, now)
        ok = True
    except Exception as exc:  # reported per run; one failing run does not stop the others
        log.warning("retention %s of run %s failed: %s", action.action, action.run_id, exc)
        detail, ok = f"{type(exc).__name__}: {exc}", False
    return Outcome(action, ok, detail, (dt.datetime.now(dt.UTC) - start).total_seconds())


def _execute(ctx: Retention, action: Action, now: dt.datetime) -> str:
    if action.action == PROMOTE:
        assert ctx.ingest is not None
        run = ctx.ingest.hot_run(action.run_id)
        if run is None:
            return "no longer hot here"
        record = promote.promote(
            run, ctx.ingest, ctx.node, now, ctx.reserve_bytes, ctx.promote_backoff, on_sealed=ctx.on_sealed
        )
        if record is None:
            return "nothing new: its chunks were all sealed already, hot copy removed"
        return f"sealed {record.chunks} chunks, {record.bytes} bytes"
    if action.action == ARCHIVE:
        return archive.archive(action.run_id, ctx.tiers, ctx.catalog, now, action.policy or "default")
    if action.action == DELETE:
        with session_scope(ctx.catalog) as session:  # a snapshot made since the plan keeps it too
            used = datasets.snapshots_using(session, [action.run_id]).get(action.run_id)
        if used:
            return f"kept: used by {datasets.describe_use(used)}"
        return _delete(ctx, action.run_id, now, "retention", action.policy)
    if action.action == RESTORE:
        return archive.advance_restore(action.run_id, ctx.tiers, ctx.catalog, now)
    raise ValueError(f"unknown action {action.action!r}")


def run_plan(ctx: Retention, actions: list[Action], progress: Callable[[Outcome], None] | None = None) -> list[Outcome]:
    outcomes = []
    for action in actions:
        outcome = execute(ctx, action)
        outcomes.append(outcome)
        if progress is not None:
            progress(outcome)
    return outcomes


# --- user actions ------------------------------------------------------------------------------


def set_pinned(ctx: Retention, run_id: str, pinned: bool, actor: str) -> dict[str, Any]:
    """Pin (exempt from expiry) or unpin a run, hot or sealed. The pin lives on the run's catalog
    row; a sealed run's run.json is rewritten from that row in the same transaction (for rebuilds),
    as promotion writes it for a hot one."""
    now = ctx.clock()
    with session_scope(ctx.catalog, write=True) as session:
        run = queries.require_run(session, run_id)
        if run.tier == Tier.DELETED:
            raise ConflictError(f"run {run_id!r} is deleted: there is nothing left to pin")
        run.pinned, run.pinned_by, run.updated_at = pinned, actor if pinned else None, now
        queries.add_event(session, run_id, "pin" if pinned else "unpin", now, actor, None)
        write_run_json(session, ctx.tiers.warm, run_id)
    return {"run": run_id, "pinned": pinned, "by": actor}


def request_restore(ctx: Retention, run_id: str, actor: str) -> dict[str, Any]:
    now = ctx.clock()
    with session_scope(ctx.catalog) as session:
        queries.require_run(session, run_id)  # 404 naming the run
    life = archive.request_restore(run_id, ctx.tiers, ctx.catalog, now, actor, ctx.restore_days)
    if life.restore_state == RestoreState.RESTORING and life.archive_mode == ARCHIVED_IN_STORE:
        # A copy back from the cold store: started now in the background rather than at the next
        # retention run; if this process stops, the retention job finishes it.
        action = Action(run_id, RESTORE, "restore asked for")
        threading.Thread(target=execute, args=(ctx, action), name=f"restore-{run_id}", daemon=True).start()
    return restore_status(life)


def restore_status(life: Any) -> dict[str, Any]:
    return {
        "run": life.run_id,
        "restore_state": life.restore_state,
        "restore_requested_at": iso_utc(life.restore_requested_at),
        "restore_until": iso_utc(life.restore_until),
    }


def upcoming(ctx: Retention) -> list[dict[str, Any]]:
    """Hot runs of this node that are not due yet, with when each will be promoted."""
    if ctx.ingest is None:
        return []
    now = ctx.clock()
    return [
        {
            "run": run.run_id,
            "action": PROMOTE,
            "at": iso_utc(at),
            "reason": why,
            "robot_id": run.robot_id or ctx.node.default_robot,
            "tier": Tier.HOT,
            "bytes": run.size,
        }
        for run, at, why in promote.upcoming(ctx.ingest, now, ctx.promote_after, ctx.promote_backoff)
    ]


def promote_now(ctx: Retention, run_id: str, actor: str = "retention") -> dict[str, Any]:
    """Seal a closed hot run now, whatever its idle time (`fleet runs promote`), as `actor` asked."""
    run = ctx.ingest.hot_run(run_id) if ctx.ingest is not None else None
    if run is None:
        with session_scope(ctx.catalog) as session:
            found = queries.require_run(session, run_id)  # 404 naming the run
            tier = found.tier
        where = "hot on another node: ask that node" if tier == Tier.HOT else f"{tier} already"
        raise ConflictError(f"run {run_id!r} is {where}: there is nothing to promote here")
    if run.status == RunStatus.LIVE or run.live_sources:
        raise ConflictError(
            f"run {run_id!r} is live (a stream is still sending it): it can be promoted once "
            "its stream ends, or FLEET_CLOSE_AFTER_S after its last data"
        )
    assert ctx.ingest is not None
    with promote.PROMOTING:
        record = promote.promote(
            run, ctx.ingest, ctx.node, ctx.clock(), ctx.reserve_bytes, ctx.promote_backoff, actor, ctx.on_sealed
        )
    if record is None:
        return {"run": run_id, "tier": Tier.WARM, "detail": "nothing new: its chunks were all sealed already"}
    return {"run": run_id, "tier": record.tier, "detail": f"sealed {record.chunks} chunks, {record.bytes} bytes"}


def delete_now(ctx: Retention, run_id: str, actor: str, force: bool = False) -> dict[str, Any]:
    """Delete a sealed run asked for by a user (`DELETE /v1/runs/{run}`); `force`: even one a
    dataset snapshot uses (whose episodes of it then answer `missing`)."""
    return {"run": run_id, "detail": delete_run(ctx, run_id, actor, force)}


def delete_run(ctx: Retention, run_id: str, actor: str, force: bool = False) -> str:
    with session_scope(ctx.catalog) as session:
        run = queries.require_run(session, run_id)
        if run.tier == Tier.HOT:
            raise ConflictError(f"run {run_id!r} is still hot: delete it once it is sealed (promoted)")
        if run.pinned:
            raise ConflictError(f"run {run_id!r} is pinned: unpin it first (fleet runs pin --unpin)")
        used = datasets.snapshots_using(session, [run_id]).get(run_id)
    if used and not force:
        raise ConflictError(
            f"run {run_id!r} is used by {datasets.describe_use(used, most=20)}: delete it anyway with "
            "force=true (`fleet runs rm --force`), and their episodes of it will answer missing"
        )
    return _delete(ctx, run_id, ctx.clock(), actor, None)


def _delete(ctx: Retention, run_id: str, now: dt.datetime, actor: str, policy: str | None) -> str:
    """Delete a sealed run (`archive.delete`), then its rows from the lakehouse's tables."""
    done = archive.delete(run_id, ctx.tiers, ctx.catalog, now, actor, policy)
    copy_now(ctx.node.lakehouse, ctx.catalog, ctx.tiers.warm, ctx.clock, [run_id])
    return done
