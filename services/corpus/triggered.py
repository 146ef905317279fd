"""A robot's agent reports a trigger it fired (`POST /v1/runs/RUN/triggered`): the event its rules
found on the robot, and the pull that brings the event's window home (`services.edge.triggers`).

The event's id is the one the depot's own evaluation gives the same finding (`event_id` of its
facts with origin rule), so the depot finding it too later keeps one event; until then it is kept
with source `robot`, and re-evaluations do not remove it. The pull id is the agent's choice, which
makes the report idempotent: sent again (its answer lost), it answers the same event and pull.
"""

from __future__ import annotations

import datetime as dt
import re
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus
from catalog import edge as edge_db
from catalog.db import session_scope
from catalog.edge import PullAsk
from catalog.models import Event, Run
from core.errors import BadParameterError
from core.states import PullState
from services.auth.scopes import Principal, Scope
from services.corpus.links import Viewer, event_answer
from services.edge.context import acting_robot, check_robot
from services.edge.copies import not_catalogued
from services.edge.pulls import Progress, check_ask
from services.edge.triggers import INT64_MAX, INT64_MIN, ROBOT, ReportedPull, take_reported_pull, trigger_pulls_made
from services.rules.triggers import PRIORITIES

PULL_ID = re.compile(r"pull-[0-9a-f]{12}")
REPORTED_STATES = (PullState.PENDING, PullState.SENDING, PullState.HELD, PullState.DONE)


@dataclass(frozen=True)
class ReportedEvent:
    """The event as the robot's rules found it (positions on its timeline, inclusive)."""

    kind: str
    severity: str
    timeline: str
    timeline_type: str
    start: int
    end: int
    label: str = ""

    def check(self) -> None:
        corpus.check_event_fields(self.kind, self.severity, self.timeline, self.label)
        if self.timeline_type not in corpus.TIMELINE_TYPES:
            raise BadParameterError(
                "timeline_type", f"{self.timeline_type!r} is not one of {', '.join(corpus.TIMELINE_TYPES)}"
            )
        for name, value in (("start", self.start), ("end", self.end)):
            if isinstance(value, bool) or not INT64_MIN <= value <= INT64_MAX:
                raise BadParameterError(name, f"{value} is no timeline position (a signed 64-bit integer)")
        if self.end < self.start:
            raise BadParameterError("end", f"{self.end} is before the start {self.start}")


@dataclass(frozen=True)
class Triggered:
    """A robot's report of a trigger it fired: the event, the window it sends, and how far it got."""

    pull_id: str
    rules_version: int
    event: ReportedEvent
    window: PullAsk
    priority: str
    state: str
    chunks_sent: int = 0
    bytes_sent: int = 0
    error: str | None = None

    def check(self) -> PullAsk:
        """Every field as the catalog takes it (422 naming the first that is not); the window checked
        as a pull's part is."""
        if not PULL_ID.fullmatch(self.pull_id):
            raise BadParameterError("pull_id", f"{self.pull_id[:80]!r} is not 'pull-' and 12 lowercase hex digits")
        if self.priority not in PRIORITIES:
            raise BadParameterError("priority", f"{self.priority!r} is not one of {', '.join(PRIORITIES)}")
        if self.state not in REPORTED_STATES:
            raise BadParameterError("state", f"{self.state!r} is not one of {', '.join(REPORTED_STATES)}")
        try:
            self.event.check()
        except BadParameterError as exc:
            raise exc.within("event") from None
        try:
            return check_ask(self.window)
        except BadParameterError as exc:
            raise exc.within("window") from None


def report_triggered(
    catalog: sessionmaker[Session],
    viewer: Viewer,
    principal: Principal,
    run_id: str,
    report: Triggered,
    now: dt.datetime,
) -> tuple[dict[str, Any], bool]:
    """Record the event (kept as it is if the depot has it already) and the pull of its window;
    `({"event": ..., "pull": ...}, whether the pull is new)`. A robot's ingest token reports on its
    own robot's runs only (403); a run the catalog does not have yet is a 404 (retry later)."""
    ask = report.check()
    bound = acting_robot(principal, Scope.WRITE)
    progress = Progress(report.state, report.chunks_sent, report.bytes_sent, report.error)
    with session_scope(catalog, write=True) as session:
        run = edge_db.run_to_pull(session, run_id)
        if run is None:
            raise not_catalogued(run_id)
        check_robot(bound, f"run {run_id!r}", run.robot_id)
        event = _event(session, run, report, now)
        reported = ReportedPull(report.pull_id, ask, report.priority, progress)
        pull, created = take_reported_pull(session, run, event.id, reported, now)
        answer = {
            "event": event_answer(event, viewer, edge_db.events_data(session, [event.id])[event.id]),
            "pull": edge_db.pull_dict(pull),
        }
    if created:
        trigger_pulls_made[ROBOT] += 1
    return answer, created


def _event(session: Session, run: Run, report: Triggered, now: dt.datetime) -> Event:
    """The reported event's row: the one the catalog holds under its id, else a new one."""
    found = report.event
    facts = corpus.EventFacts(
        kind=found.kind,
        severity=found.severity,
        timeline=found.timeline,
        timeline_type=found.timeline_type,
        start=found.start,
        end=found.end,
        origin=corpus.RULE,
        source=corpus.REPORTED_BY_ROBOT,
        label=found.label,
    )
    ident = corpus.event_id(run.id, facts)
    held = corpus.get_event(session, ident)
    if held is not None:
        return held
    return corpus.add_event(session, run.id, run.robot_id, facts, now, ident, report.rules_version)
