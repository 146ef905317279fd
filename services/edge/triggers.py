"""Trigger pulls: the full data of a window around an event, brought home from the robot's agent by
itself, and a person's pull of an event's window.

A trigger pull is queued two ways, each in the caller's transaction:

- by the depot's live rules, for each new event a `[[trigger]]` of the running rules names
  (`queue_trigger_pulls`): its window on the event's timeline is [start - before, end + after],
  `before_s`/`after_s` in ns on timestamp and duration timelines, and taken as a count of steps on
  a sequence timeline (a frame number has no length in seconds). Several triggers naming the same
  event make one pull: their includes together, the widest window, the higher priority. An event
  whose trigger pull exists already (its robot reported it first) gets none; a window overlapping
  or touching the window of a pending trigger pull of the same run, timeline and include widens that
  pull (which keeps its first event) instead of making another;
- by the robot's agent that fired the trigger, reporting it (`take_reported_pull`, called by the
  corpus's `POST /v1/runs/RUN/triggered`): the pull id it chose, or the depot's pull of the same
  event if the depot fired first.

`fleet_trigger_pulls_total{origin}` counts the trigger pulls made (`robot`: reported, `depot`:
queued by the live rules), in this process.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session

from catalog import corpus as corpus_db
from catalog import edge as edge_queries
from catalog.db import session_scope
from catalog.edge import TRIGGER, PullAsk, PullOrigin
from catalog.models import Event, Pull, Run
from core.errors import ConflictError, NotFoundError
from core.states import PullState, Tier
from services.edge.context import Edge
from services.edge.pulls import FINAL, Progress, apply_progress, new_pull_id, plain_error, pullable_run
from services.rules.triggers import TriggerRule

NS_PER_S = 1_000_000_000
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1
DEPOT, ROBOT = "depot", "robot"  # who queued a trigger pull (the counter's `origin`)
HIGH, NORMAL = "high", "normal"

# Trigger pulls made in this process, by who queued them (read by /metrics at each scrape).
trigger_pulls_made: Counter[str] = Counter()


# --- the window of a trigger around an event -----------------------------------------------------


@dataclass(frozen=True)
class TriggerWindow:
    """What a trigger pull asks of the run: positions on the event's timeline, the entities."""

    timeline: str
    start: int
    end: int
    include: list[str]
    priority: str


def steps(seconds: float, timeline_type: str) -> int:
    """`seconds` on a timeline of this type: ns on timestamp and duration timelines, a count of
    steps (rounded up) on a sequence one."""
    if timeline_type == "sequence":
        return math.ceil(seconds)
    return round(seconds * NS_PER_S)


def trigger_window(triggers: Sequence[TriggerRule], event: Event) -> TriggerWindow:
    """The window of these triggers (all naming the event's kind) around the event."""
    before = max(steps(t.before_s, event.timeline_type) for t in triggers)
    after = max(steps(t.after_s, event.timeline_type) for t in triggers)
    include = list(dict.fromkeys(p for t in triggers for p in t.include))
    priority = HIGH if any(t.priority == HIGH for t in triggers) else NORMAL
    start = max(INT64_MIN, event.range_start - before)
    end = min(INT64_MAX, event.range_end + after)
    return TriggerWindow(event.timeline, start, end, include, priority)


# --- queued by the depot's live rules ---------------------------------------------------------------


def queue_trigger_pulls(
    session: Session, run: Run, events: Sequence[Event], triggers: Sequence[TriggerRule], version: int, now: dt.datetime
) -> int:
    """Queue (or widen) a trigger pull for each of the run's new `events` a trigger names; how many
    pulls it made. None for a run without a robot, or one that takes no data (cold, deleted)."""
    by_kind: dict[str, list[TriggerRule]] = {}
    for trigger in triggers:
        for kind in trigger.events:
            by_kind.setdefault(kind, []).append(trigger)
    named = sorted((e for e in events if e.kind in by_kind), key=lambda e: (e.range_start, e.id))
    if not named or not run.robot_id or run.tier in (Tier.COLD, Tier.DELETED):
        return 0
    edge_queries.run_to_pull(session, run.id)  # locked: a robot's report of the same event waits
    made = 0
    for event in named:
        if edge_queries.trigger_pull_of(session, event.id) is not None:
            continue  # its robot reported it first
        window = trigger_window(by_kind[event.kind], event)
        if _widened(session, run.id, window, now):
            continue
        ask = PullAsk(run.id, window.include, [], window.timeline, str(window.start), str(window.end))
        made_by = PullOrigin(TRIGGER, event.id, window.priority)
        by = f"trigger {event.kind}@{version}"
        edge_queries.add_pull(session, new_pull_id(), ask, run.robot_id, by, now, made_by)
        made += 1
    return made


def _widened(session: Session, run_id: str, window: TriggerWindow, now: dt.datetime) -> bool:
    """Whether a pending trigger pull of the run whose window overlaps or touches this one took it
    (widened to cover both)."""
    for pull in edge_queries.pending_trigger_pulls(session, run_id, window.timeline, window.include):
        held = _positions(pull)
        if held is None or window.start > held[1] + 1 or held[0] > window.end + 1:
            continue
        pull.start, pull.end = str(min(held[0], window.start)), str(max(held[1], window.end))
        if window.priority == HIGH:
            pull.priority = HIGH
        pull.updated_at = now
        session.flush()
        return True
    return False


def _positions(pull: Pull) -> tuple[int, int] | None:
    try:
        return int(pull.start or ""), int(pull.end or "")
    except ValueError:  # a robot's reported window written otherwise: never widened
        return None


# --- reported by the robot's agent ------------------------------------------------------------------


@dataclass(frozen=True)
class ReportedPull:
    """The pull a robot's agent says it made for a trigger it fired (its ask checked by the caller)."""

    pull_id: str
    ask: PullAsk
    priority: str
    progress: Progress  # its state (pending, sending, held or done) and counters


_AHEAD = {PullState.PENDING: 0, PullState.SENDING: 1, PullState.HELD: 2, PullState.DONE: 2}


def take_reported_pull(
    session: Session, run: Run, event_id: str, reported: ReportedPull, now: dt.datetime
) -> tuple[Pull, bool]:
    """The pull a robot's report of a trigger it fired stands for, and whether it is new: the pull
    of that id (of this run, else 409) moved as its report says, unless it is past that already (a
    report sent again); else the depot's trigger pull of the same event (moved out of pending only);
    else a new trigger pull in the reported state."""
    progress = reported.progress
    pull = edge_queries.get_pull(session, reported.pull_id, for_update=True)
    if pull is not None:
        if pull.run_id != run.id:
            raise ConflictError(
                f"pull {reported.pull_id!r} is a pull of run {pull.run_id!r}, not of {run.id!r}: choose another id"
            )
        if pull.state not in FINAL and _AHEAD[PullState(progress.state)] >= _AHEAD[PullState(pull.state)]:
            apply_progress(pull, progress, now)
            session.flush()
        return pull, False
    fired = edge_queries.trigger_pull_of(session, event_id, run_id=run.id)
    if fired is not None:  # the depot fired first: the agent reports progress on that pull
        if fired.state == PullState.PENDING and progress.state != PullState.PENDING:
            apply_progress(fired, progress, now)
            session.flush()
        return fired, False
    made_by = PullOrigin(TRIGGER, event_id, reported.priority, progress.state)
    pull = edge_queries.add_pull(
        session, reported.pull_id, reported.ask, run.robot_id, f"robot {run.robot_id}", now, made_by
    )
    pull.chunks_sent, pull.bytes_sent = progress.chunks_sent, progress.bytes_sent
    pull.error = plain_error(progress.error)
    session.flush()
    return pull, True


# --- a person pulls an event's window ---------------------------------------------------------------


def pull_event(edge: Edge, event_id: str, requested_by: str) -> tuple[dict[str, Any], bool]:
    """`POST /v1/events/EVENT/pull`: a person's pull of the window the event's newest trigger pull
    asked for (`({"pull": ...}, True)`), or its pending or sending pull (`(..., False)`). 404 for an
    unknown event; 409 for one no trigger pulled (no window is known of it) or whose run takes no
    data."""
    with session_scope(edge.catalog, write=True) as session:
        event = corpus_db.get_event(session, event_id)
        if event is None:
            raise NotFoundError(f"no event {event_id!r}: list events with GET /v1/events or `fleet events ls`")
        run = pullable_run(session, event.run_id)
        open_pull = edge_queries.open_pull_of(session, event_id)
        if open_pull is not None:
            return {"pull": edge_queries.pull_dict(open_pull)}, False
        fired = edge_queries.trigger_pull_of(session, event_id)
        if fired is None:
            raise ConflictError(
                f"event {event_id!r} was pulled by no trigger, so no window of it is known: ask for a window "
                f"of its run with POST /v1/runs/{event.run_id}/pull (fleet runs pull {event.run_id} --timeline "
                f"{event.timeline} --start ... --end ...)"
            )
        ask = PullAsk(
            run.id, json.loads(fired.include), json.loads(fired.exclude), fired.timeline, fired.start, fired.end
        )
        made_by = PullOrigin(event_id=event_id)
        pull = edge_queries.add_pull(session, new_pull_id(), ask, run.robot_id, requested_by, edge.clock(), made_by)
        return {"pull": edge_queries.pull_dict(pull)}, True
