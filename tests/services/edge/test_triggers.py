"""Trigger pulls on the depot's side: the window around an event on each kind of timeline, one pull
per event (none when the robot reported it first), pending windows widened instead of doubled, none
for a run that takes no data or names no robot; held pulls; and a person's pull of an event's
window (a twin answered, refused without a window)."""

from __future__ import annotations

import datetime as dt
import json
from typing import Any

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus
from catalog import edge as edge_queries
from catalog.db import session_scope
from catalog.edge import TRIGGER, PullAsk, PullOrigin
from catalog.models import Event, Pull, Run
from core.errors import ConflictError, NotFoundError
from services.edge.context import Edge
from services.edge.pulls import Progress, cancel_pull, report_progress, request_pull
from services.edge.triggers import pull_event, queue_trigger_pulls, steps, trigger_window
from services.rules.triggers import TriggerRule
from tests.services.edge.conftest import ROBOT, add_run, refused, robot_token

RUN = "triggered-run"
S = 1_000_000_000
T0 = 1_700_000_000 * S
CAMERA = TriggerRule(events=("hard_brake",), include=("/camera/**",), before_s=10, after_s=5, priority="normal")
AT = dt.datetime(2026, 11, 30, 8, 0, tzinfo=dt.UTC)


@pytest.fixture
def run(catalog: sessionmaker[Session]) -> str:
    add_run(catalog, RUN, robot=ROBOT)
    return RUN


def event(
    catalog: sessionmaker[Session],
    start: int,
    end: int | None = None,
    *,
    kind: str = "hard_brake",
    run_id: str = RUN,
    timeline: str = "log_time",
    timeline_type: str = "timestamp",
) -> str:
    """A rule's event on the run, as an evaluation writes it; its id."""
    facts = corpus.EventFacts(
        kind, "warn", timeline, timeline_type, start, start if end is None else end, corpus.RULE, f"rule {kind}@3"
    )
    ident = corpus.event_id(run_id, facts)
    with session_scope(catalog, write=True) as session:
        corpus.add_event(session, run_id, ROBOT, facts, AT, ident, 3)
    return ident


def fire(catalog: sessionmaker[Session], event_ids: list[str], triggers: list[TriggerRule], run_id: str = RUN) -> int:
    """What the live rules do with new events: queue their trigger pulls."""
    with session_scope(catalog, write=True) as session:
        run = session.get(Run, run_id)
        assert run is not None
        events = [session.get(Event, ident) for ident in event_ids]
        return queue_trigger_pulls(session, run, [e for e in events if e is not None], triggers, 3, AT)


def trigger_pulls(catalog: sessionmaker[Session], run_id: str = RUN) -> list[dict[str, Any]]:
    with session_scope(catalog) as session:
        return [edge_queries.pull_dict(p) for p in edge_queries.run_pulls(session, run_id) if p.origin == TRIGGER]


def test_a_window_is_seconds_on_time_timelines_and_steps_on_sequence_ones():
    assert steps(10, "timestamp") == steps(10, "duration") == 10 * S
    assert steps(0.25, "timestamp") == S // 4
    assert steps(10, "sequence") == 10 and steps(2.5, "sequence") == 3  # a count of steps, rounded up
    wide = TriggerRule(events=("hard_brake",), include=("/lidar/**", "/camera/**"), before_s=2, after_s=30)
    high = TriggerRule(events=("hard_brake",), include=("/camera/**",), before_s=1, after_s=1, priority="high")
    brake = Event(kind="hard_brake", timeline="frame", timeline_type="sequence", range_start=100, range_end=104)
    window = trigger_window([CAMERA, wide, high], brake)
    assert (window.timeline, window.start, window.end) == ("frame", 90, 134)  # the widest of them
    assert window.include == ["/camera/**", "/lidar/**"] and window.priority == "high"
    edge = Event(kind="k", timeline="t", timeline_type="timestamp", range_start=-(2**63) + 5, range_end=2**63 - 5)
    clamped = trigger_window([CAMERA], edge)
    assert (clamped.start, clamped.end) == (-(2**63), 2**63 - 1)  # kept within signed 64 bits


def test_a_new_event_a_trigger_names_queues_its_window(edge: Edge, catalog: sessionmaker[Session], run: str):
    brake = event(catalog, T0, T0 + S // 10)
    other = event(catalog, T0 + 100 * S, kind="stuck")  # no trigger names it
    assert fire(catalog, [brake, other], [CAMERA]) == 1
    (pull,) = trigger_pulls(catalog)
    assert pull == {
        **pull,
        "run_id": RUN,
        "robot_id": ROBOT,
        "include": ["/camera/**"],
        "exclude": [],
        "timeline": "log_time",
        "start": str(T0 - 10 * S),
        "end": str(T0 + S // 10 + 5 * S),
        "state": "pending",
        "requested_by": "trigger hard_brake@3",
        "origin": "trigger",
        "event_id": brake,
        "priority": "normal",
    }
    assert fire(catalog, [brake], [CAMERA]) == 0  # the same event again: its pull stands
    assert len(trigger_pulls(catalog)) == 1


def test_an_overlapping_or_touching_window_widens_the_pending_pull(
    edge: Edge, catalog: sessionmaker[Session], run: str
):
    first = event(catalog, T0)
    assert fire(catalog, [first], [CAMERA]) == 1  # [T0 - 10 s, T0 + 5 s]
    overlapping = event(catalog, T0 + 12 * S)  # [T0 + 2 s, T0 + 17 s]
    touching = event(catalog, T0 + 17 * S + 10 * S + 1)  # starts 1 ns after the widened pull's end
    high = TriggerRule(events=("hard_brake",), include=("/camera/**",), before_s=10, after_s=5, priority="high")
    assert fire(catalog, [overlapping, touching], [high]) == 0
    (pull,) = trigger_pulls(catalog)
    assert (pull["start"], pull["end"]) == (str(T0 - 10 * S), str(T0 + 27 * S + 1 + 5 * S))
    assert pull["event_id"] == first and pull["priority"] == "high"  # its first event; the higher priority

    apart = event(catalog, T0 + 1000 * S)  # far off: a pull of its own
    lidar = TriggerRule(events=("hard_brake",), include=("/lidar/**",), before_s=10, after_s=5)
    beside = event(catalog, T0 + 1, kind="hard_brake", timeline="log_time")
    assert fire(catalog, [apart], [CAMERA]) == 1
    assert fire(catalog, [beside], [lidar]) == 1  # another include: not the camera pull
    assert len(trigger_pulls(catalog)) == 3


def test_a_pull_that_is_no_longer_pending_is_not_widened(edge: Edge, catalog: sessionmaker[Session], run: str):
    first = event(catalog, T0)
    fire(catalog, [first], [CAMERA])
    (pull,) = trigger_pulls(catalog)
    report_progress(edge, robot_token(), pull["id"], Progress("sending", 1, 10))
    assert fire(catalog, [event(catalog, T0 + S)], [CAMERA]) == 1  # the agent sends the first window as it was
    assert {p["id"]: p["start"] for p in trigger_pulls(catalog)}[pull["id"]] == pull["start"]


def test_the_robots_pull_of_an_event_stands(edge: Edge, catalog: sessionmaker[Session], run: str):
    brake = event(catalog, T0)
    ask = PullAsk(RUN, ["/camera/**"], [], "log_time", str(T0 - S), str(T0 + S))
    with session_scope(catalog, write=True) as session:
        edge_queries.add_pull(session, "pull-0000000000aa", ask, ROBOT, "robot robot-7", AT, PullOrigin(TRIGGER, brake))
    assert fire(catalog, [brake], [CAMERA]) == 0
    assert [p["id"] for p in trigger_pulls(catalog)] == ["pull-0000000000aa"]


@pytest.mark.parametrize(("tier", "robot"), [("cold", ROBOT), ("deleted", ROBOT), ("warm", "")])
def test_no_trigger_pull_for_a_run_that_takes_no_data_or_has_no_robot(
    edge: Edge, catalog: sessionmaker[Session], tier: str, robot: str
):
    add_run(catalog, "elsewhere", robot=robot, tier=tier)
    assert fire(catalog, [event(catalog, T0, run_id="elsewhere")], [CAMERA], run_id="elsewhere") == 0
    assert trigger_pulls(catalog, "elsewhere") == []


# --- held -------------------------------------------------------------------------------------------


def test_a_held_pull_takes_no_report_until_a_person_dismisses_it(edge: Edge, catalog: sessionmaker[Session], run: str):
    fire(catalog, [event(catalog, T0)], [CAMERA])
    pending = trigger_pulls(catalog)[0]["id"]
    held = report_progress(edge, robot_token(), pending, Progress("held", 0, 0, "over budget: 500000000 bytes today"))
    assert (held["pull"]["state"], held["pull"]["error"]) == ("held", "over budget: 500000000 bytes today")
    for state in ("sending", "done", "held"):
        with refused(ConflictError, 409, f"pull '{pending}' is held"):
            report_progress(edge, robot_token(), pending, Progress(state, 0, 0))
    assert cancel_pull(edge, pending)["pull"]["state"] == "cancelled"  # dismissed

    sending = request_pull(edge, PullAsk(RUN, ["/a"], [], None, None, None), "alice")[0]["pull"]["id"]
    report_progress(edge, robot_token(), sending, Progress("sending", 3, 300))
    assert report_progress(edge, robot_token(), sending, Progress("held", 3, 300))["pull"]["state"] == "held"


# --- a person pulls an event's window -----------------------------------------------------------------


def test_a_person_pulls_the_window_a_trigger_asked_for(edge: Edge, catalog: sessionmaker[Session], run: str):
    brake = event(catalog, T0)
    fire(catalog, [brake], [CAMERA])
    fired = trigger_pulls(catalog)[0]
    report_progress(edge, robot_token(), fired["id"], Progress("held", 0, 0, "over budget"))
    answer, created = pull_event(edge, brake, "alice")
    pulled = answer["pull"]
    assert created and pulled["id"] != fired["id"]
    assert {k: pulled[k] for k in ("origin", "event_id", "requested_by", "state", "priority")} == {
        "origin": "person",
        "event_id": brake,
        "requested_by": "alice",
        "state": "pending",
        "priority": None,
    }
    assert {k: pulled[k] for k in ("include", "exclude", "timeline", "start", "end")} == {
        k: fired[k] for k in ("include", "exclude", "timeline", "start", "end")
    }
    again, created = pull_event(edge, brake, "bob")  # pending: that pull, not a twin
    assert not created and again["pull"]["id"] == pulled["id"]


def test_an_event_no_trigger_pulled_has_no_window_to_pull(edge: Edge, catalog: sessionmaker[Session], run: str):
    brake = event(catalog, T0)
    with refused(ConflictError, 409, "pulled by no trigger", f"POST /v1/runs/{RUN}/pull"):
        pull_event(edge, brake, "alice")
    with refused(NotFoundError, 404, "no event 'ev-0000000000000000'"):
        pull_event(edge, "ev-0000000000000000", "alice")
    with session_scope(catalog) as session:
        assert session.query(Pull).count() == 0


def test_pulls_answer_says_where_they_come_from(edge: Edge, catalog: sessionmaker[Session], run: str):
    brake = event(catalog, T0)
    fire(catalog, [brake], [CAMERA])
    with session_scope(catalog) as session:
        (row,) = edge_queries.run_pulls(session, RUN)
        assert (row.origin, row.event_id, row.priority) == ("trigger", brake, "normal")
        assert json.loads(row.include) == ["/camera/**"]
