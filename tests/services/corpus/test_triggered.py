"""Triggers over REST with auth on, through the REST client: a robot's agent reports one it fired
(the event and its pull, idempotent, its own robot's runs only, every bad field named), the depot's
own pull answered when it fired first; re-evaluations keep a robot's event; where each event's
window is (`data`), the events still to come (`?pending=true`), and a person's pull of an event."""

from __future__ import annotations

import datetime as dt
import re
import secrets
from typing import Any

import pytest
from prometheus_client.parser import text_string_to_metric_families

from catalog import corpus
from catalog import edge as edge_db
from catalog.db import session_scope
from catalog.edge import TRIGGER, PullAsk, PullOrigin
from catalog.models import Pull
from tests.services.auth.conftest import Depot, bearer
from tests.services.corpus.conftest import T0, add_run, catalog_of, refused, sdk

S = 1_000_000_000
ROBOT, OTHER = "robot-7", "robot-a"
AT = dt.datetime(2026, 11, 30, 8, 0, tzinfo=dt.UTC)


def report(pull_id: str = "pull-0123456789ab", **changes: Any) -> dict[str, Any]:
    body: dict[str, Any] = {
        "pull_id": pull_id,
        "rules_version": 3,
        "event": {
            "kind": "hard_brake",
            "severity": "warn",
            "timeline": "log_time",
            "timeline_type": "timestamp",
            "start": T0 + 10 * S,
            "end": T0 + 10 * S + S // 10,
            "label": "",
        },
        "window": {
            "timeline": "log_time",
            "start": str(T0),
            "end": str(T0 + 15 * S + S // 10),
            "include": ["/camera/**"],
            "exclude": [],
        },
        "priority": "high",
        "state": "sending",
        "chunks_sent": 0,
        "bytes_sent": 0,
        "error": None,
    }
    return {**body, **changes}


def rule_facts(body: dict[str, Any], source: str = "rule hard_brake@3") -> corpus.EventFacts:
    e = body["event"]
    return corpus.EventFacts(
        e["kind"], e["severity"], e["timeline"], e["timeline_type"], e["start"], e["end"], corpus.RULE, source
    )


def test_a_robot_reports_a_trigger_it_fired_once_however_often_it_sends_it(depot: Depot):
    add_run(depot, "run-a", robot=ROBOT)
    robot = sdk(depot, depot.token("ingest", robot=ROBOT))
    body = report()
    answered = depot.client.post(
        "/v1/runs/run-a/triggered", json=body, headers=bearer(depot.token("ingest", robot=ROBOT))
    )
    assert answered.status_code == 201, answered.text
    made = answered.json()
    event, pull = made["event"], made["pull"]
    assert event["id"] == corpus.event_id("run-a", rule_facts(body))  # the id the depot's rules would give it
    assert {k: event[k] for k in ("run_id", "robot_id", "kind", "origin", "source", "rules_version", "start")} == {
        "run_id": "run-a",
        "robot_id": ROBOT,
        "kind": "hard_brake",
        "origin": "rule",
        "source": "robot",
        "rules_version": 3,
        "start": T0 + 10 * S,
    }
    assert "/v1/runs/run-a/recording.rrd?timeline=log_time" in event["viewer_url"]
    assert pull == {
        **pull,
        "id": "pull-0123456789ab",
        "run_id": "run-a",
        "robot_id": ROBOT,
        "include": ["/camera/**"],
        "timeline": "log_time",
        "start": str(T0),
        "state": "sending",
        "requested_by": f"robot {ROBOT}",
        "origin": "trigger",
        "event_id": event["id"],
        "priority": "high",
    }
    assert event["data"] == {
        "state": "pending",
        "pulls": [
            {
                "id": pull["id"],
                "origin": "trigger",
                "state": "sending",
                "chunks_sent": 0,
                "bytes_sent": 0,
                "error": None,
            }
        ],
    }
    again = robot.report_triggered("run-a", body)  # its answer lost: sent again
    assert {**again["pull"], "updated_at": None} == {**pull, "updated_at": None}  # (when it last heard: now)
    assert again["event"]["id"] == event["id"]
    later = robot.report_triggered("run-a", {**body, "chunks_sent": 4, "bytes_sent": 4000})
    assert (later["pull"]["state"], later["pull"]["chunks_sent"]) == ("sending", 4)  # the same state: counters
    done = robot.pull_progress(pull["id"], state="done", chunks_sent=9, bytes_sent=9000)
    assert done["state"] == "done"
    stale = robot.report_triggered("run-a", {**body, "state": "pending"})  # an older report: the pull as it is
    assert (stale["pull"]["state"], stale["pull"]["chunks_sent"]) == ("done", 9)
    assert robot.report_triggered("run-a", body)["event"]["data"]["state"] == "held"  # at the depot
    with session_scope(catalog_of(depot)) as session:
        assert session.query(Pull).count() == 1
        assert len(corpus.events_of_run(session, "run-a")) == 1
    reported = _samples(depot)
    assert reported.get(("robot",), 0) >= 1


def _samples(depot: Depot) -> dict[tuple[str, ...], float]:
    text = depot.client.get("/metrics", headers=bearer(depot.token("read"))).text
    return {
        tuple(s.labels.values()): s.value
        for f in text_string_to_metric_families(text)
        for s in f.samples
        if s.name == "fleet_trigger_pulls_total"
    }


def test_a_report_counts_one_trigger_pull_made_by_a_robot(depot: Depot):
    add_run(depot, "run-a", robot=ROBOT)
    robot = sdk(depot, depot.token("ingest", robot=ROBOT))
    before = _samples(depot)
    assert set(before) == {("depot",), ("robot",)}
    robot.report_triggered("run-a", report())
    robot.report_triggered("run-a", report())  # the same again: no other pull
    assert _samples(depot)[("robot",)] == before[("robot",)] + 1


def test_the_depots_pull_is_answered_when_it_fired_first(depot: Depot):
    add_run(depot, "run-a", robot=ROBOT)
    body = report(state="held", error="over budget: 500000000 bytes today")
    ident = corpus.event_id("run-a", rule_facts(body))
    with session_scope(catalog_of(depot), write=True) as session:
        corpus.add_event(session, "run-a", ROBOT, rule_facts(body), AT, ident, 3)
        ask = PullAsk("run-a", ["/camera/**"], [], "log_time", str(T0 - S), str(T0 + 20 * S))
        made_by = PullOrigin(TRIGGER, ident, "normal")
        edge_db.add_pull(session, "pull-depot0000001", ask, ROBOT, "trigger hard_brake@3", AT, made_by)
    answer = sdk(depot, depot.token("ingest", robot=ROBOT)).report_triggered("run-a", body)
    assert answer["pull"]["id"] == "pull-depot0000001"  # the agent reports progress on that one
    assert (answer["pull"]["state"], answer["pull"]["start"]) == ("held", str(T0 - S))  # its window kept
    assert answer["event"]["source"] == "rule hard_brake@3"  # the depot's event, as it was
    assert answer["event"]["data"]["state"] == "held on robot: over budget"
    with session_scope(catalog_of(depot)) as session:
        assert [p.id for p in edge_db.run_pulls(session, "run-a")] == ["pull-depot0000001"]


def test_a_robot_reports_on_its_own_runs_and_catalogued_ones_only(depot: Depot):
    add_run(depot, "run-a", robot=ROBOT)
    theirs = sdk(depot, depot.token("ingest", robot=OTHER))
    refused(lambda: theirs.report_triggered("run-a", report()), 403, f"belongs to robot '{ROBOT}'", OTHER)
    robot = sdk(depot, depot.token("ingest", robot=ROBOT))
    refused(lambda: robot.report_triggered("not-yet", report()), 404, "retry later")
    refused(lambda: sdk(depot, depot.token("read")).report_triggered("run-a", report()), 403, "'ingest' or 'write'")
    assert sdk(depot, depot.token("write")).report_triggered("run-a", report())["pull"]["robot_id"] == ROBOT
    add_run(depot, "run-b", robot=ROBOT)
    refused(lambda: robot.report_triggered("run-b", report()), 409, "is a pull of run 'run-a'")


EVENT, WINDOW = report()["event"], report()["window"]


@pytest.mark.parametrize(
    ("changes", "named"),
    [
        ({"pull_id": "pull-XYZ"}, "pull_id"),
        ({"pull_id": "other-0123456789ab"}, "pull_id"),
        ({"priority": "urgent"}, "priority"),
        ({"state": "failed"}, "state"),
        ({"rules_version": 0}, "rules_version"),
        ({"rules_version": "3"}, "rules_version"),
        ({"chunks_sent": -1}, "chunks_sent"),
        ({"colour": "red"}, "colour"),
        ({"event": {**EVENT, "kind": "two words"}}, "event.kind"),
        ({"event": {**EVENT, "severity": "fatal"}}, "event.severity"),
        ({"event": {**EVENT, "timeline": ""}}, "event.timeline"),
        ({"event": {**EVENT, "timeline": "log\x00time"}}, "event.timeline"),
        ({"event": {**EVENT, "timeline_type": "clock"}}, "event.timeline_type"),
        ({"event": {**EVENT, "end": EVENT["start"] - 1}}, "event.end"),
        ({"event": {**EVENT, "start": 2**63}}, "event.start"),
        ({"event": {**EVENT, "start": True}}, "event.start"),
        ({"event": {**EVENT, "label": "x" * 1001}}, "event.label"),
        ({"event": {k: v for k, v in EVENT.items() if k != "kind"}}, "event.kind"),
        ({"window": {**WINDOW, "include": ["camera/**"]}}, "window.include"),
        ({"window": {**WINDOW, "include": [7]}}, "window.include[0]"),
        ({"window": {**WINDOW, "timeline": None}}, "window.timeline"),
        ({"window": {**WINDOW, "start": "x" * 2000}}, "window.start"),
        ({"window": None}, "window"),
    ],
)
def test_a_bad_report_is_one_422_naming_the_field(depot: Depot, changes: dict[str, Any], named: str):
    add_run(depot, "run-a", robot=ROBOT)
    answer = depot.client.post(
        "/v1/runs/run-a/triggered", json=report(**changes), headers=bearer(depot.token("ingest", robot=ROBOT))
    )
    assert answer.status_code == 422, answer.text
    assert f"parameter '{named}'" in answer.json()["message"], answer.json()
    with session_scope(catalog_of(depot)) as session:
        assert session.query(Pull).count() == 0 and corpus.events_of_run(session, "run-a") == []


def test_a_re_evaluation_keeps_the_robots_event_until_it_finds_it_itself(depot: Depot):
    add_run(depot, "run-a", robot=ROBOT)
    body = report()
    reported = sdk(depot, depot.token("ingest", robot=ROBOT)).report_triggered("run-a", body)["event"]

    def evaluate(found: list[corpus.EventFacts]) -> list[str]:
        with session_scope(catalog_of(depot), write=True) as session:
            new = corpus.replace_evaluation(
                session,
                run_id="run-a",
                robot_id=ROBOT,
                rules_version=3,
                state="final",
                events=found,
                metrics=[],
                capped=False,
                note=None,
                now=AT,
            )
            return [e.id for e in new]

    elsewhere = corpus.EventFacts("stuck", "error", "log_time", "timestamp", T0, T0, corpus.RULE, "rule stuck@3")
    assert evaluate([elsewhere]) == [corpus.event_id("run-a", elsewhere)]
    reader = sdk(depot, depot.token("read"))
    kept = {e["id"]: e for e in reader.run_events("run-a")}
    assert kept[reported["id"]]["source"] == "robot"  # not found by the depot: kept all the same
    assert evaluate([rule_facts(body), elsewhere]) == [reported["id"]]  # found: the rule's now, told of once
    assert reader.event(reported["id"])["source"] == "rule hard_brake@3"
    assert evaluate([elsewhere]) == []  # the depot's own event now: replaced as its evaluations say
    assert reported["id"] not in {e["id"] for e in reader.run_events("run-a")}


# --- where an event's window is --------------------------------------------------------------------


def _event_with_pulls(depot: Depot, start: int, pulls: list[tuple[str, int]]) -> str:
    """A rule's event with pulls in these (state, chunks sent); its id."""
    facts = corpus.EventFacts("stuck", "error", "log_time", "timestamp", start, start, corpus.RULE, "rule stuck@3")
    ident = corpus.event_id("run-a", facts)
    with session_scope(catalog_of(depot), write=True) as session:
        corpus.add_event(session, "run-a", ROBOT, facts, AT, ident, 3)
        for i, (state, chunks) in enumerate(pulls):
            ask = PullAsk("run-a", [], [], "log_time", str(start - S), str(start + S))
            at = AT + dt.timedelta(seconds=i)
            made_by = PullOrigin(TRIGGER, ident)
            pull = edge_db.add_pull(session, f"pull-{secrets.token_hex(6)}", ask, ROBOT, "x", at, made_by)
            pull.state, pull.chunks_sent = state, chunks
    return ident


@pytest.mark.parametrize(
    ("pulls", "state", "pending"),
    [
        ([], None, False),
        ([("done", 5)], "held", False),
        ([("pending", 0)], "pending", True),
        ([("sending", 2)], "pending", True),
        ([("failed", 3)], "partly held", False),
        ([("cancelled", 1)], "partly held", False),
        ([("held", 0)], "held on robot: over budget", True),
        ([("failed", 0)], "on robot", False),
        ([("cancelled", 0)], "on robot", False),
        ([("held", 0), ("done", 9)], "held", False),  # the best of its pulls
        ([("failed", 0), ("held", 0)], "held on robot: over budget", True),
        ([("held", 0), ("sending", 1)], "pending", True),
        ([("failed", 2), ("held", 0)], "partly held", True),
    ],
)
def test_an_events_data_is_the_best_state_of_its_pulls(
    depot: Depot, pulls: list[tuple[str, int]], state: str | None, pending: bool
):
    add_run(depot, "run-a", robot=ROBOT)
    ident = _event_with_pulls(depot, T0, pulls)
    other = _event_with_pulls(depot, T0 + S, [("held", 0)])
    reader = sdk(depot, depot.token("read"))
    shown = reader.event(ident)["data"]
    assert (shown["state"] if shown else None) == state
    if shown:
        assert [p["state"] for p in shown["pulls"]] == [s for s, _ in pulls][::-1]  # newest first
        assert set(shown["pulls"][0]) == {"id", "origin", "state", "chunks_sent", "bytes_sent", "error"}
    listed = {e["id"]: e["data"] for e in reader.events()["events"]}
    assert listed[ident] == shown and {e["id"]: e["data"] for e in reader.run_events("run-a")}[ident] == shown
    waiting = [e["id"] for e in reader.events(pending=True)["events"]]
    assert (ident in waiting) == pending and other in waiting


def test_event_answers_read_their_pulls_in_one_query(depot: Depot, monkeypatch):
    add_run(depot, "run-a", robot=ROBOT)
    for i in range(5):
        _event_with_pulls(depot, T0 + i * S, [("held", 0), ("pending", 0)])
    calls: list[int] = []
    real = edge_db.event_pulls

    def counted(session, event_ids):  # type: ignore[no-untyped-def]
        calls.append(len(event_ids))
        return real(session, event_ids)

    monkeypatch.setattr(edge_db, "event_pulls", counted)
    page = sdk(depot, depot.token("read")).events()["events"]
    assert len(page) == 5 and calls == [5]
    assert {e["data"]["state"] for e in page} == {"pending"}


# --- a person pulls an event's window ---------------------------------------------------------------


def test_a_person_pulls_an_events_window_over_rest(depot: Depot):
    add_run(depot, "run-a", robot=ROBOT)
    robot = sdk(depot, depot.token("ingest", robot=ROBOT))
    held = robot.report_triggered("run-a", report(state="held", error="over budget: 1 byte left"))
    event_id = held["event"]["id"]
    alice_token = depot.token("write", name="alice")
    alice = sdk(depot, alice_token)
    pulled = alice.pull_event(event_id)
    assert (pulled["origin"], pulled["event_id"], pulled["requested_by"]) == ("person", event_id, "alice")
    assert (pulled["timeline"], pulled["start"], pulled["include"]) == ("log_time", str(T0), ["/camera/**"])
    twin = depot.client.post(f"/v1/events/{event_id}/pull", headers=bearer(alice_token))
    assert twin.status_code == 200 and twin.json() == {"pull": pulled}
    assert sdk(depot, depot.token("read")).event(event_id)["data"]["state"] == "pending"
    assert [p["id"] for p in robot.pulls(state="pending")] == [pulled["id"]]  # what its agent polls

    annotated = alice.annotate("run-a", "log_time", str(T0), label="look here")
    refused(lambda: alice.pull_event(annotated["id"]), 409, "pulled by no trigger", "POST /v1/runs/run-a/pull")
    refused(lambda: alice.pull_event("ev-0000000000000000"), 404, "no event")
    refused(lambda: robot.pull_event(event_id), 403, "'write'")
    assert re.fullmatch(r"pull-[0-9a-f]{12}", pulled["id"])
