"""The depot's live rules fire triggers: each new event a `[[trigger]]` names queues a pull of the
window around it for the run's robot, in the transaction that writes the event; overlapping windows
widen one pending pull; an event whose robot reported it first gets none from the depot."""

from __future__ import annotations

import io
from typing import Any

from catalog import corpus as corpus_db
from catalog import edge as edge_db
from catalog.db import session_scope
from catalog.edge import TRIGGER, PullAsk, PullOrigin
from services.edge import triggers
from services.rrd import iter_events
from tests.services.corpus.pipeline import scene as expect
from tests.services.corpus.pipeline.conftest import Depot, DepotFactory
from tests.services.ingest import feeding
from tests.waiting import wait_for

S = 1_000_000_000


def rules(before_s: float, after_s: float) -> str:
    return (
        expect.RULES_V1
        + f"""
[[trigger]]
event = "intervention"
include = ["/world/**", "/sensors/**"]
before_s = {before_s}
after_s = {after_s}
priority = "high"
"""
    )


def pulls(depot: Depot, run_id: str) -> list[dict[str, Any]]:
    with session_scope(depot.node.catalog) as session:
        found = [edge_db.pull_dict(p) for p in edge_db.run_pulls(session, run_id)]
    return sorted(found, key=lambda p: int(p["start"]))


def stream(depot: Depot, scene, run_id: str) -> None:
    """The scene fed as a live stream (the run stays hot), its catalog row written."""
    source = depot.ingest.open_source(live=True)
    feeding.feed(depot.ingest, source, iter_events(io.BytesIO(scene(run_id))))
    depot.ingest.flush_catalog()


def interventions(depot: Depot, run_id: str) -> list[Any]:
    found = sorted((e for e in depot.events(run_id) if e.kind == "intervention"), key=lambda e: e.range_start)
    return found if len(found) == len(expect.expected_interventions()) else []


def test_overlapping_windows_of_new_events_are_one_pending_pull(make_depot: DepotFactory, scene):
    depot = make_depot(catalog_flush_s=0.1)
    version = depot.apply(rules(before_s=10, after_s=5))  # windows of 25 s around events 15 s apart
    made_before = triggers.trigger_pulls_made[triggers.DEPOT]
    run_id = "corpus-triggers-merged"
    stream(depot, scene, run_id)
    events = wait_for(lambda: interventions(depot, run_id), timeout=30, what="the live interventions")
    (first, *_), last = events, events[-1]
    assert first.timeline_type == "timestamp"
    want = (str(first.range_start - 10 * S), str(last.range_end + 5 * S))

    def widened() -> list[dict[str, Any]] | None:
        found = pulls(depot, run_id)
        return found if found and (found[0]["start"], found[0]["end"]) == want else None

    (pull,) = wait_for(widened, timeout=30, what="one pull widened over every window")
    assert {k: pull[k] for k in ("origin", "event_id", "priority", "state", "requested_by", "timeline")} == {
        "origin": "trigger",
        "event_id": first.id,  # the first event's
        "priority": "high",
        "state": "pending",
        "requested_by": f"trigger intervention@{version}",
        "timeline": first.timeline,
    }
    assert pull["include"] == ["/world/**", "/sensors/**"] and pull["robot_id"] == first.robot_id != ""
    # counted once its transaction committed, just after the pull became visible
    wait_for(lambda: triggers.trigger_pulls_made[triggers.DEPOT] == made_before + 1, timeout=10, what="the count")
    assert triggers.trigger_pulls_made[triggers.DEPOT] == made_before + 1


def test_apart_windows_are_pulls_of_their_own_and_a_robots_report_stands(make_depot: DepotFactory, scene):
    depot = make_depot(catalog_flush_s=0.1)
    version = depot.apply(rules(before_s=1, after_s=1))
    run_id = "corpus-triggers-apart"
    first_start, first_end = expect.expected_interventions()[0]
    reported = corpus_db.event_id(
        run_id,
        corpus_db.EventFacts(
            "intervention", "warn", "sim_time", "timestamp", first_start, first_end, corpus_db.RULE, "robot"
        ),
    )
    with session_scope(depot.node.catalog, write=True) as session:  # its robot reported the first one
        ask = PullAsk(run_id, ["/world/**"], [], "sim_time", str(first_start), str(first_end))
        made_by = PullOrigin(TRIGGER, reported, "high", "sending")
        edge_db.add_pull(session, "pull-00000000robo", ask, "robot-c", "robot robot-c", depot.node.clock(), made_by)
    stream(depot, scene, run_id)
    events = wait_for(lambda: interventions(depot, run_id), timeout=30, what="the live interventions")
    assert events[0].id == reported

    def three() -> list[dict[str, Any]] | None:
        found = pulls(depot, run_id)
        return found if len(found) == 3 else None

    found = wait_for(three, timeout=30, what="three pulls")
    assert found[0]["id"] == "pull-00000000robo"  # the robot's, untouched
    assert [(p["event_id"], p["start"], p["end"]) for p in found[1:]] == [
        (e.id, str(e.range_start - S), str(e.range_end + S)) for e in events[1:]
    ]
    assert {p["requested_by"] for p in found[1:]} == {f"trigger intervention@{version}"}
