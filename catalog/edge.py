"""Catalog reads and writes of what the depot knows of robots' own tiers: pulls queued for their
agents (a person's, or a trigger's window around an event), and the copies of runs their agents
report holding; both as the JSON answers show them (shared by `GET /v1/runs/RUN` and the edge
routes), and where an event's window is (`event_data`, what every event answer says)."""

from __future__ import annotations

import datetime as dt
import json
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.models import Pull, RobotCopy, Run
from core.clock import iso_utc
from core.states import PullState

OPEN_STATES = (PullState.PENDING, PullState.SENDING)  # what an agent may still be working on
# An event whose pulls are in these states, none done, has its window still to come (`?pending=true`).
AWAITED_STATES = (PullState.PENDING, PullState.SENDING, PullState.HELD)
RUN_PAGE_PULLS = 10  # pulls a run's page shows
PERSON, TRIGGER = "person", "trigger"  # a pull's origin


def _locks_rows(session: Session) -> bool:
    """Postgres locks a row read for update; the embedded catalog serializes writers instead
    (`session_scope(write=True)`) and has no locking clause."""
    return session.get_bind().dialect.name == "postgresql"


# --- pulls ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PullAsk:
    """What a pull asks for: the run, and the part of it (as given; checked by the caller)."""

    run_id: str
    include: list[str]
    exclude: list[str]
    timeline: str | None
    start: str | None
    end: str | None


def run_to_pull(session: Session, run_id: str) -> Run | None:
    """The run a pull is asked of, locked until the transaction ends (on Postgres): of two requests
    for the same part at once, the second sees the first's pull and answers it."""
    return session.get(Run, run_id, with_for_update=_locks_rows(session))


def open_twin(session: Session, ask: PullAsk) -> Pull | None:
    """A pending or sending pull of the run that asks for the very same part, if there is one."""
    query = sa.select(Pull).where(
        Pull.run_id == ask.run_id,
        Pull.state.in_(OPEN_STATES),
        Pull.include == json.dumps(ask.include),
        Pull.exclude == json.dumps(ask.exclude),
        _same(Pull.timeline, ask.timeline),
        _same(Pull.start, ask.start),
        _same(Pull.end, ask.end),
    )
    return session.scalars(query.order_by(Pull.requested_at, Pull.id).limit(1)).first()


def _same(column: Any, value: str | None) -> sa.ColumnElement[bool]:
    return column.is_(None) if value is None else column == value  # type: ignore[no-any-return]


@dataclass(frozen=True)
class PullOrigin:
    """Who a pull is for: a person's (no event, or the event they pulled) or a trigger's window
    around an event, in the state the pull starts in (a trigger's, as its agent reports it)."""

    origin: str = PERSON
    event_id: str | None = None
    priority: str | None = None
    state: str = PullState.PENDING


def add_pull(
    session: Session,
    pull_id: str,
    ask: PullAsk,
    robot_id: str,
    requested_by: str,
    now: dt.datetime,
    made: PullOrigin = PullOrigin(),
) -> Pull:
    pull = Pull(
        id=pull_id,
        run_id=ask.run_id,
        robot_id=robot_id,
        include=json.dumps(ask.include),
        exclude=json.dumps(ask.exclude),
        timeline=ask.timeline,
        start=ask.start,
        end=ask.end,
        state=made.state,
        requested_by=requested_by,
        requested_at=now,
        updated_at=now,
        chunks_sent=0,
        bytes_sent=0,
        error=None,
        origin=made.origin,
        event_id=made.event_id,
        priority=made.priority,
    )
    session.add(pull)
    session.flush()
    return pull


def get_pull(session: Session, pull_id: str, *, for_update: bool = False) -> Pull | None:
    """A pull by id; `for_update`: locked until the transaction ends (on Postgres), so a progress
    report and a cancel never both change it from the state they read."""
    return session.get(Pull, pull_id, with_for_update=for_update and _locks_rows(session))


def run_pulls(session: Session, run_id: str, limit: int | None = None) -> list[Pull]:
    """A run's pulls, newest first."""
    query = sa.select(Pull).where(Pull.run_id == run_id).order_by(Pull.requested_at.desc(), Pull.id.desc())
    return list(session.scalars(query if limit is None else query.limit(limit)))


def queued_pulls(session: Session, *, robot: str | None, state: str | None, limit: int) -> list[Pull]:
    """Pulls of one robot (None: of every robot) in one state (None: any), oldest first: the
    order an agent works through them."""
    query = sa.select(Pull)
    if robot is not None:
        query = query.where(Pull.robot_id == robot)
    if state is not None:
        query = query.where(Pull.state == state)
    return list(session.scalars(query.order_by(Pull.requested_at, Pull.id).limit(limit)))


def pull_dict(pull: Pull) -> dict[str, Any]:
    return {
        "id": pull.id,
        "run_id": pull.run_id,
        "robot_id": pull.robot_id,
        "include": json.loads(pull.include),
        "exclude": json.loads(pull.exclude),
        "timeline": pull.timeline,
        "start": pull.start,
        "end": pull.end,
        "state": pull.state,
        "requested_by": pull.requested_by,
        "requested_at": iso_utc(pull.requested_at),
        "updated_at": iso_utc(pull.updated_at),
        "chunks_sent": pull.chunks_sent,
        "bytes_sent": pull.bytes_sent,
        "error": pull.error,
        "origin": pull.origin,
        "event_id": pull.event_id,
        "priority": pull.priority,
    }


# --- pulls of events ------------------------------------------------------------------------------


def event_pulls(session: Session, event_ids: Sequence[str]) -> dict[str, list[Pull]]:
    """The pulls of each of these events (one query), newest first; an event without any is left out."""
    found: dict[str, list[Pull]] = {}
    if not event_ids:
        return found
    query = (
        sa.select(Pull)
        .where(Pull.event_id.in_(list(dict.fromkeys(event_ids))))
        .order_by(Pull.requested_at.desc(), Pull.id.desc())
    )
    for pull in session.scalars(query):
        found.setdefault(str(pull.event_id), []).append(pull)
    return found


def trigger_pull_of(session: Session, event_id: str, *, run_id: str | None = None) -> Pull | None:
    """The newest trigger pull of the event (of run `run_id`, if given), if there is one."""
    query = sa.select(Pull).where(Pull.event_id == event_id, Pull.origin == TRIGGER)
    if run_id is not None:
        query = query.where(Pull.run_id == run_id)
    return session.scalars(query.order_by(Pull.requested_at.desc(), Pull.id.desc()).limit(1)).first()


def open_pull_of(session: Session, event_id: str) -> Pull | None:
    """A pending or sending pull of the event (the oldest), if there is one."""
    query = sa.select(Pull).where(Pull.event_id == event_id, Pull.state.in_(OPEN_STATES))
    return session.scalars(query.order_by(Pull.requested_at, Pull.id).limit(1)).first()


def pending_trigger_pulls(session: Session, run_id: str, timeline: str, include: list[str]) -> list[Pull]:
    """The run's pending trigger pulls of this timeline and include, nothing excluded: those a new
    window may widen (locked until the transaction ends, on Postgres), oldest first."""
    query = sa.select(Pull).where(
        Pull.run_id == run_id,
        Pull.origin == TRIGGER,
        Pull.state == PullState.PENDING,
        Pull.timeline == timeline,
        Pull.include == json.dumps(include),
        Pull.exclude == json.dumps([]),
    )
    query = query.order_by(Pull.requested_at, Pull.id)
    return list(session.scalars(query.with_for_update() if _locks_rows(session) else query))


# Where an event's window is, best first: at the depot (a pull is done), on its way (a pull is
# pending or sending), partly at the depot (a pull stopped after sending some), kept on the robot
# over its trigger's budget (held), or only on the robot (every pull stopped before sending any).
AT_DEPOT, ON_ITS_WAY, PARTLY_AT_DEPOT = "held", "pending", "partly held"
OVER_BUDGET, ON_ROBOT = "held on robot: over budget", "on robot"
DATA_STATES = (AT_DEPOT, ON_ITS_WAY, PARTLY_AT_DEPOT, OVER_BUDGET, ON_ROBOT)


def data_state(pull: Pull) -> str:
    if pull.state == PullState.DONE:
        return AT_DEPOT
    if pull.state in OPEN_STATES:
        return ON_ITS_WAY
    if pull.state == PullState.HELD:
        return OVER_BUDGET
    return PARTLY_AT_DEPOT if pull.chunks_sent > 0 else ON_ROBOT  # failed or cancelled


def event_data(pulls: Sequence[Pull]) -> dict[str, Any] | None:
    """What an event answer says of its window (`data`): None with no pull of it, else the best
    state over its pulls and the pulls (newest first, as given)."""
    if not pulls:
        return None
    return {
        "state": min((data_state(p) for p in pulls), key=DATA_STATES.index),
        "pulls": [
            {
                "id": p.id,
                "origin": p.origin,
                "state": p.state,
                "chunks_sent": p.chunks_sent,
                "bytes_sent": p.bytes_sent,
                "error": p.error,
            }
            for p in pulls
        ],
    }


def events_data(session: Session, event_ids: Sequence[str]) -> dict[str, dict[str, Any] | None]:
    """`event_data` of each of these events, read in one query."""
    found = event_pulls(session, event_ids)
    return {ident: event_data(found.get(ident, [])) for ident in event_ids}


# --- robot copies ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class RobotCopyReport:
    """What a robot's agent says it holds of a run (checked by the caller)."""

    run_id: str
    robot_id: str
    reported_at: dt.datetime
    chunks: int
    bytes: int
    local_only_chunks: int
    local_only_bytes: int
    local_only_entities: list[str]
    keeps_until: dt.datetime | None


def save_robot_copy(session: Session, report: RobotCopyReport) -> RobotCopy:
    """Store the latest report of a run's robot copy (replacing the one before)."""
    row = session.get(RobotCopy, report.run_id, with_for_update=_locks_rows(session))
    if row is None:
        row = RobotCopy(run_id=report.run_id)
        session.add(row)
    row.robot_id, row.reported_at = report.robot_id, report.reported_at
    row.chunks, row.bytes = report.chunks, report.bytes
    row.local_only_chunks, row.local_only_bytes = report.local_only_chunks, report.local_only_bytes
    row.local_only_entities = json.dumps(report.local_only_entities)
    row.keeps_until = report.keeps_until
    session.flush()
    return row


def robot_copy(session: Session, run_id: str) -> RobotCopy | None:
    return session.get(RobotCopy, run_id)


def remove_robot_copy(session: Session, run_id: str) -> bool:
    """Forget a run's robot copy (its robot deleted it); whether there was one."""
    row = session.get(RobotCopy, run_id, with_for_update=_locks_rows(session))
    if row is None:
        return False  # DuckDB's row counts of a DELETE cannot be relied on: look first
    session.delete(row)
    session.flush()
    return True


def robot_copy_dict(row: RobotCopy) -> dict[str, Any]:
    return {
        "run_id": row.run_id,
        "robot_id": row.robot_id,
        "reported_at": iso_utc(row.reported_at),
        "chunks": row.chunks,
        "bytes": row.bytes,
        "local_only_chunks": row.local_only_chunks,
        "local_only_bytes": row.local_only_bytes,
        "local_only_entities": json.loads(row.local_only_entities),
        "keeps_until": iso_utc(row.keeps_until),
    }


def run_edge(session: Session, run_id: str) -> dict[str, Any]:
    """What a run's page says of the robot's own copy and the pulls of the run (the latest few)."""
    row = robot_copy(session, run_id)
    return {
        "robot_copy": robot_copy_dict(row) if row is not None else None,
        "pulls": [pull_dict(p) for p in run_pulls(session, run_id, RUN_PAGE_PULLS)],
    }
