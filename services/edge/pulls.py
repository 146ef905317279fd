"""Pulls: an engineer asks that a robot's agent send (part of) a run it holds; the agent polls for
its robot's pending pulls and reports its progress.

States: pending -> sending -> done | failed, pending -> failed; pending or sending -> held (the
agent keeps the window on the robot: over its trigger's budget, `error` saying so); a report of the
state a pull is in already only updates its counters. Pending or sending -> cancelled by whoever may
request pulls, and held -> cancelled (a person dismisses it). A done, failed, cancelled or held pull
takes no report (409 naming its state). Asking again for what a pending or sending pull of the same
run already asks for answers that pull, not a twin.
"""

from __future__ import annotations

import datetime as dt
import logging
import secrets
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session

from catalog import edge as edge_queries
from catalog import queries
from catalog.db import session_scope
from catalog.edge import PullAsk
from catalog.models import Pull, Run
from core.errors import BadParameterError, ConflictError, NotFoundError, PermissionDeniedError
from core.ids import NAME_BYTES
from core.states import PullState, Tier
from services.auth.scopes import Principal, Scope
from services.edge.context import Edge, acting_robot, check_robot
from services.rrd.entity_patterns import check_entity_patterns

log = logging.getLogger("fleet.edge")

MAX_LIMIT = 1000
MAX_ERROR_CHARS = 2000
REPORTED = (PullState.SENDING, PullState.DONE, PullState.FAILED, PullState.HELD)  # what an agent reports
MOVES = {
    PullState.PENDING: {PullState.SENDING, PullState.FAILED, PullState.HELD},
    PullState.SENDING: {PullState.SENDING, PullState.DONE, PullState.FAILED, PullState.HELD},
}
FINAL = (PullState.DONE, PullState.FAILED, PullState.CANCELLED, PullState.HELD)


def new_pull_id() -> str:
    return "pull-" + secrets.token_hex(6)


def pull_not_found(pull_id: str) -> NotFoundError:
    return NotFoundError(f"no pull {pull_id!r}: GET /v1/runs/RUN/pulls or `fleet runs pulls RUN` lists a run's pulls")


def check_ask(ask: PullAsk) -> PullAsk:
    """The part of a run a pull asks for, checked as a download checks it; empty strings as none."""
    check_entity_patterns("include", ask.include)
    check_entity_patterns("exclude", ask.exclude)
    timeline, start, end = (value or None for value in (ask.timeline, ask.start, ask.end))
    for name, value in (("timeline", timeline), ("start", start), ("end", end)):
        if value is not None and ("\x00" in value or len(value.encode("utf-8", "surrogatepass")) > NAME_BYTES):
            raise BadParameterError(
                name, f"{value[:80]!r} is no timeline name or position (NUL, or over {NAME_BYTES} bytes)"
            )
    if timeline is None and (start is not None or end is not None):
        raise BadParameterError(
            "timeline", "start and end are positions on a timeline: name it too (e.g. frame, log_time)"
        )
    return PullAsk(ask.run_id, list(ask.include), list(ask.exclude), timeline, start, end)


def request_pull(edge: Edge, ask: PullAsk, requested_by: str) -> tuple[dict[str, Any], bool]:
    """Queue a pull of `ask.run_id` for its robot's agent: `({"pull": ...}, True)`, or the pending
    or sending pull that asks for the same part, `(..., False)`. 404 for a run the catalog does not
    have; 409 for one that takes no data (cold or deleted)."""
    ask = check_ask(ask)
    with session_scope(edge.catalog, write=True) as session:
        run = pullable_run(session, ask.run_id)
        twin = edge_queries.open_twin(session, ask)
        if twin is not None:
            return {"pull": edge_queries.pull_dict(twin)}, False
        pull = edge_queries.add_pull(session, new_pull_id(), ask, run.robot_id, requested_by, edge.clock())
        return {"pull": edge_queries.pull_dict(pull)}, True


def pullable_run(session: Session, run_id: str) -> Run:
    """The run a person pulls, locked until the transaction ends (on Postgres): 404 for a run the
    catalog does not have; 409 for one that takes no data (cold or deleted) or names no robot."""
    run = edge_queries.run_to_pull(session, run_id)
    if run is None:
        raise queries.run_not_found(run_id)
    if run.tier in (Tier.COLD, Tier.DELETED):
        fix = f"restore it first (fleet runs restore {run.id})" if run.tier == Tier.COLD else "nothing can be"
        raise ConflictError(f"run {run.id!r} is {run.tier}: it takes no data, so no pull; {fix}")
    if not run.robot_id:
        raise ConflictError(f"run {run.id!r} names no robot: there is no agent to pull it from")
    return run


def run_pulls_answer(edge: Edge, run_id: str) -> dict[str, Any]:
    """`GET /v1/runs/RUN/pulls`: the run's pulls, newest first (404 for a run the catalog lacks)."""
    with session_scope(edge.catalog) as session:
        queries.require_run(session, run_id)
        return {"pulls": [edge_queries.pull_dict(p) for p in edge_queries.run_pulls(session, run_id)]}


@dataclass(frozen=True)
class PullQuery:
    state: str | None = None
    robot: str | None = None
    limit: int = 100


def pulls_answer(edge: Edge, principal: Principal, query: PullQuery) -> dict[str, Any]:
    """`GET /v1/pulls`: pulls by state and robot, oldest first (the order an agent works through
    them). A robot's ingest token sees its own robot's only, the default."""
    if query.state is not None and query.state not in tuple(PullState):
        raise BadParameterError("state", f"{query.state!r} is not one of {', '.join(PullState)}")
    if not 1 <= query.limit <= MAX_LIMIT:
        raise BadParameterError("limit", f"{query.limit} is not between 1 and {MAX_LIMIT}")
    bound = acting_robot(principal, Scope.READ)
    robot = query.robot or bound
    if bound is not None and robot != bound:
        raise PermissionDeniedError(
            f"this token acts for robot {bound!r} only: it lists that robot's pulls, not those of robot {robot!r}"
        )
    with session_scope(edge.catalog) as session:
        found = edge_queries.queued_pulls(session, robot=robot, state=query.state, limit=query.limit)
        return {"pulls": [edge_queries.pull_dict(p) for p in found]}


@dataclass(frozen=True)
class Progress:
    state: str
    chunks_sent: int
    bytes_sent: int
    error: str | None = None


def report_progress(edge: Edge, principal: Principal, pull_id: str, progress: Progress) -> dict[str, Any]:
    """`POST /v1/pulls/PULL/progress`: the agent's state and counters (a robot's ingest token for
    its own robot's pulls, or write)."""
    if progress.state not in REPORTED:
        raise BadParameterError("state", f"{progress.state!r} is not one of {', '.join(REPORTED)}")
    bound = acting_robot(principal, Scope.WRITE)
    with session_scope(edge.catalog, write=True) as session:
        pull = _existing(session, pull_id)
        check_robot(bound, f"pull {pull_id!r}", pull.robot_id)
        _refuse_if_final(pull)
        if progress.state not in MOVES[PullState(pull.state)]:
            raise ConflictError(
                f"pull {pull_id!r} is {pull.state}: it can go to {', '.join(sorted(MOVES[PullState(pull.state)]))}, "
                f"not {progress.state} (a pull is sending before it is done)"
            )
        apply_progress(pull, progress, edge.clock())
        session.flush()
        return {"pull": edge_queries.pull_dict(pull)}


def apply_progress(pull: Pull, progress: Progress, now: dt.datetime) -> None:
    """A report's state and counters on the pull (the move checked by the caller)."""
    if progress.state != pull.state:  # the access line of a report is DEBUG (services/routine_logs.py)
        log.info("pull %s of run %s: %s -> %s", pull.id, pull.run_id, pull.state, progress.state)
    pull.state, pull.updated_at = progress.state, now
    pull.chunks_sent, pull.bytes_sent = progress.chunks_sent, progress.bytes_sent
    pull.error = plain_error(progress.error)


def cancel_pull(edge: Edge, pull_id: str) -> dict[str, Any]:
    """`POST /v1/pulls/PULL/cancel`: a pending, sending or held pull is cancelled (again: as it
    is); a done or failed one is a 409 naming its state."""
    with session_scope(edge.catalog, write=True) as session:
        pull = _existing(session, pull_id)
        if pull.state in (PullState.DONE, PullState.FAILED):
            raise ConflictError(f"pull {pull_id!r} is {pull.state} already: there is nothing to cancel")
        if pull.state != PullState.CANCELLED:
            pull.state, pull.updated_at = PullState.CANCELLED, edge.clock()
            session.flush()
        return {"pull": edge_queries.pull_dict(pull)}


def _existing(session: Session, pull_id: str) -> Pull:
    pull = edge_queries.get_pull(session, pull_id, for_update=True)
    if pull is None:
        raise pull_not_found(pull_id)
    return pull


def _refuse_if_final(pull: Pull) -> None:
    if pull.state in FINAL:
        stop = "stop sending it" if pull.state == PullState.CANCELLED else "it takes no more reports"
        raise ConflictError(f"pull {pull.id!r} is {pull.state}: {stop}")


def plain_error(error: str | None) -> str | None:
    """An agent's error message as the catalog keeps it: no NUL, at most MAX_ERROR_CHARS."""
    if error is None:
        return None
    return error.replace("\x00", "\ufffd")[:MAX_ERROR_CHARS]
