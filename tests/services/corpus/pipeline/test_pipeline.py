"""The rules over runs, in one node: live while hot, final at sealing, again after a rules change
by the backfill (replaced, never doubled, resumable, throttled, reading only what rules name; cold
runs skipped), with the values a test computes itself from what the scene logged."""

from __future__ import annotations

import asyncio
import datetime as dt
import io
from collections import Counter

import pytest
from sqlalchemy.orm import Session

from catalog import corpus, webhooks
from catalog.corpus import EvaluationFacts
from catalog.db import session_scope
from catalog.models import Event
from catalog.webhooks import WebhookRecord
from services.api.metrics import LiveRulesCollector
from services.corpus import evaluation, live
from services.corpus.backfill import Pace, due_runs
from services.corpus.evaluation import COLD_NOTE
from services.retention import archive
from services.rrd import iter_events
from tests.services.corpus.pipeline import scene as expect
from tests.services.corpus.pipeline.conftest import Depot, DepotFactory
from tests.services.ingest import feeding
from tests.waiting import wait_for


def kinds(depot: Depot, run_id: str) -> dict[str, list[tuple[int, int]]]:
    found: dict[str, list[tuple[int, int]]] = {}
    for event in depot.events(run_id):
        found.setdefault(event.kind, []).append((event.range_start, event.range_end))
    return found


def assert_v1_values(depot: Depot, run_id: str, version: int) -> None:
    events = depot.events(run_id)
    by_kind = kinds(depot, run_id)
    assert sorted(by_kind["intervention"]) == expect.expected_interventions()
    assert sorted(s for s, _ in by_kind["stuck"]) == expect.expected_stuck()
    (brake,) = [e for e in events if e.kind == "hard_brake"]
    assert (brake.origin, brake.source, brake.label, brake.severity) == ("robot", "robot", "brake!", "warn")
    assert {e.source for e in events if e.kind == "intervention"} == {f"rule intervention@{version}"}
    assert len(events) == 3 + 2 + 1  # nothing doubled
    metrics = depot.metrics(run_id)
    assert metrics["distance_m"][0] == pytest.approx(expect.expected_distance())
    assert metrics["temp_mean"][0] == pytest.approx(expect.expected_temp_mean())
    assert metrics["interventions"][0] == 3
    assert metrics["sw_version"][1] == expect.SW_VERSION
    assert {m[2] for m in metrics.values()} == {version}


def test_a_run_has_its_values_while_hot_and_final_ones_once_sealed(make_depot: DepotFactory, scene, monkeypatch):
    def unread(recording: object) -> None:
        raise AssertionError("a run ingest started is evaluated from its chunks, its file never read")

    monkeypatch.setattr(live, "open_hot", unread)
    depot = make_depot(catalog_flush_s=0.1)
    version = depot.apply(expect.RULES_V1)
    run_id = "corpus-live"
    source = depot.ingest.open_source(live=True)
    feeding.feed(depot.ingest, source, iter_events(io.BytesIO(scene(run_id))))
    depot.ingest.flush_catalog()  # the run's catalog row, as the housekeeping writes it

    def live_values() -> object:
        found = kinds(depot, run_id)
        return found if len(found.get("intervention", [])) == 3 and "distance_m" in depot.metrics(run_id) else None

    wait_for(live_values, timeout=30, what="live events and metrics of the hot run")
    evaluated = depot.evaluation(run_id)
    assert evaluated is not None and (evaluated.state, evaluated.rules_version) == ("live", version)
    assert sorted(live_values()["intervention"]) == expect.expected_interventions()  # type: ignore[index]
    cost = {family.name: family.samples[0].value for family in LiveRulesCollector(depot.ingest).collect()}
    assert cost["fleet_live_rules_chunks"] == depot.corpus.live.evaluated_chunks > 0
    assert cost["fleet_live_rules_cpu_seconds"] > 0 and cost["fleet_live_rules_dropped_chunks"] == 0

    asyncio.run(depot.ingest.end_source(source))
    depot.seal(run_id)
    wait_final(depot, run_id)
    assert_v1_values(depot, run_id, version)
    assert depot.corpus.sealing.from_live == 1  # the live evaluator saw every wanted chunk: nothing read
    assert depot.corpus.sealing.reads.bytes_read == 0
    assert depot.tags(run_id) == {"night-shift": "robot", "dock-2": "robot"}


def wait_final(depot: Depot, run_id: str) -> None:
    wait_for(lambda: (e := depot.evaluation(run_id)) is not None and e.state == "final", timeout=30, what="final")


def sealed(depot: Depot, scene, run_id: str) -> None:
    depot.upload(scene(run_id))
    depot.seal(run_id)
    wait_final(depot, run_id)


def test_a_rules_change_and_backfill_replace_the_values(make_depot: DepotFactory, scene):
    depot = make_depot()
    depot.apply(expect.RULES_V1)
    sealed(depot, scene, "corpus-change")
    assert_v1_values(depot, "corpus-change", 1)

    version = depot.apply(expect.RULES_V2)
    summary = depot.corpus.backfill.run()
    assert summary is not None and (summary.evaluated, summary.failed) == (1, 0)
    evaluated = depot.evaluation("corpus-change")
    assert evaluated is not None and (evaluated.state, evaluated.rules_version) == ("final", version)
    events = depot.events("corpus-change")
    interventions = [e for e in events if e.kind == "intervention"]
    assert sorted((e.range_start, e.range_end) for e in interventions) == expect.expected_interventions()
    assert {(e.severity, e.source) for e in interventions} == {("error", f"rule intervention@{version}")}
    assert sorted(e.kind for e in events) == ["hard_brake", "intervention", "intervention", "intervention"]
    metrics = depot.metrics("corpus-change")
    assert list(metrics) == ["temp_max"] and metrics["temp_max"][1:] == (None, version)
    assert metrics["temp_max"][0] == pytest.approx(expect.expected_temp_max())

    again = depot.corpus.backfill.run()  # every run is at the running version: nothing is read
    assert again is not None and (again.total, again.bytes_read) == (0, 0)


def test_the_backfill_resumes_where_it_was_killed(make_depot: DepotFactory, scene):
    depot = make_depot()
    for run_id in ("corpus-r1", "corpus-r2", "corpus-r3"):
        sealed(depot, scene, run_id)  # at version 0: robots' events only
    depot.apply(expect.RULES_V1)

    class Killed(Exception):
        pass

    done: list[str] = []

    def killed_after_one(event: dict[str, object]) -> None:
        if event["event"] == "run":
            done.append(str(event["run"]))
            raise Killed

    with pytest.raises(Killed):
        depot.corpus.backfill.run(killed_after_one)
    assert len(done) == 1

    read: list[str] = []
    summary = depot.corpus.backfill.run(lambda e: read.append(e["run"]) if e["event"] == "run" else None)
    assert summary is not None and summary.evaluated == 2
    assert sorted(read + done) == ["corpus-r1", "corpus-r2", "corpus-r3"]  # the first is not read again
    for run_id in ("corpus-r1", "corpus-r2", "corpus-r3"):
        assert_v1_values(depot, run_id, 1)


def test_only_the_entities_rules_name_are_read(make_depot: DepotFactory, scene):
    depot = make_depot()
    sealed(depot, scene, "corpus-ranged")
    depot.apply(expect.RULES_V1)
    summary = depot.corpus.backfill.run()
    assert summary is not None and summary.evaluated == 1
    recording = len(scene("corpus-ranged"))
    assert 0 < summary.bytes_read < recording * 0.05  # the point clouds (97 % of it) are never fetched
    assert_v1_values(depot, "corpus-ranged", 1)


def test_a_cold_run_is_reported_skipped(make_depot: DepotFactory, scene):
    depot = make_depot()
    sealed(depot, scene, "corpus-cold")
    node = depot.node
    archive.archive("corpus-cold", node.tiers, node.catalog, node.clock(), "default")
    depot.apply(expect.RULES_V1)
    summary = depot.corpus.backfill.run()
    assert summary is not None and (summary.skipped_cold, summary.evaluated, summary.bytes_read) == (1, 0, 0)
    evaluated = depot.evaluation("corpus-cold")
    assert evaluated is not None and (evaluated.state, evaluated.note, evaluated.rules_version) == (
        "skipped",
        COLD_NOTE,
        1,
    )


def test_a_full_queue_never_blocks_ingest_and_the_sealed_run_is_read_instead(make_depot: DepotFactory, scene):
    depot = make_depot(start=False, queue_chunks=1)  # nothing takes chunks off the queue
    depot.apply(expect.RULES_V1)
    depot.corpus.live.reload_rules()
    report = depot.upload(scene("corpus-full"))  # returns: ingest never waited
    assert report.chunks_new > 10 and depot.corpus.live.dropped_chunks > 0
    depot.corpus.start()
    depot.seal("corpus-full")
    wait_for(
        lambda: (e := depot.evaluation("corpus-full")) is not None and e.state == "final", timeout=30, what="final"
    )
    assert depot.corpus.sealing.from_live == 0 and depot.corpus.sealing.reads.bytes_read > 0
    assert_v1_values(depot, "corpus-full", 1)


def test_robot_tags_from_a_list_or_a_comma_separated_string():
    assert evaluation.robot_tags({"fleet": {"tags": ["b", "a", " a "]}}) == ["a", "b"]
    assert evaluation.robot_tags({"fleet": {"tags": "night-shift, dock-2,"}}) == ["dock-2", "night-shift"]
    assert evaluation.robot_tags({"fleet": {"robot_id": "r"}}) == []


def test_the_pace_holds_reads_to_the_rate():
    slept: list[float] = []
    pace = Pace(1000, slept.append)
    pace(5000)
    assert slept and slept[0] == pytest.approx(5.0, abs=0.2)


def test_a_failed_seal_evaluation_is_left_to_the_backfill(make_depot: DepotFactory, scene, monkeypatch):
    depot = make_depot()
    depot.apply(expect.RULES_V1)
    monkeypatch.setattr(
        "services.corpus.sealing.finish_run", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("catalog down"))
    )
    depot.upload(scene("corpus-retry"))
    assert depot.seal("corpus-retry")["tier"] == "warm"  # the seal stands
    wait_for(lambda: depot.corpus.sealing.failures == 1, timeout=30, what="the sealing's evaluation to fail")
    monkeypatch.undo()
    with session_scope(depot.node.catalog) as session:
        assert "corpus-retry" in due_runs(session, 1)
    summary = depot.corpus.backfill.run()
    assert summary is not None and summary.evaluated == 1
    assert_v1_values(depot, "corpus-retry", 1)


def test_a_rule_stops_at_the_cap_and_says_so(make_depot: DepotFactory, scene):
    depot = make_depot(max_events_per_run=2)
    depot.apply(expect.RULES_V1)
    sealed(depot, scene, "corpus-capped")
    evaluated = depot.evaluation("corpus-capped")
    assert evaluated is not None and evaluated.events_capped
    assert evaluated.note is not None and "FLEET_MAX_EVENTS_PER_RUN" in evaluated.note
    assert len(depot.events("corpus-capped")) == 2


def test_webhooks_are_told_of_the_seal_and_of_each_event_once(make_depot: DepotFactory, scene):
    depot = make_depot(catalog_flush_s=0.1)
    now = depot.node.clock()
    with session_scope(depot.node.catalog, write=True) as session:
        hook = WebhookRecord("wh-000000000001", "http://127.0.0.1:9/", ("run.sealed", "event:*"), "json", "x", "t", now)
        webhooks.add_webhook(session, hook)
    depot.apply(expect.RULES_V1)
    depot.upload(scene("corpus-hooks"))
    depot.seal("corpus-hooks")
    wait_final(depot, "corpus-hooks")
    depot.apply(expect.RULES_V2)
    depot.corpus.backfill.run()  # the same interventions found again: not told again
    with session_scope(depot.node.catalog) as session:
        told = Counter(d.occurrence for d in webhooks.deliveries(session, hook.id, limit=100)[0])
    assert told == {"run.sealed": 1, "event:intervention": 3, "event:stuck": 2, "event:hard_brake": 1}


def test_a_hot_run_whose_metrics_alone_move_is_written_every_few_flushes(make_depot: DepotFactory, scene, monkeypatch):
    depot = make_depot(start=False)  # the test drives the worker's steps itself
    depot.apply('[[metric]]\nname = "distance_m"\nkind = "path_length"\nentity = "/world/robot"\n')
    live_rules = depot.corpus.live
    live_rules.reload_rules()
    writes: list[str] = []
    write = corpus.replace_evaluations

    def counted(session: Session, facts: list[EvaluationFacts], now: dt.datetime) -> list[Event]:
        writes.extend(f.run_id for f in facts)
        return write(session, facts, now)

    monkeypatch.setattr(live, "replace_evaluations", counted)

    def take_queued() -> None:
        while live_rules._queue:
            live_rules._take(live_rules._queue.popleft())

    events = list(iter_events(io.BytesIO(scene("corpus-metrics"))))
    source = depot.ingest.open_source(live=True)
    feeding.feed(depot.ingest, source, events[: len(events) // 2])
    depot.ingest.flush_catalog()
    take_queued()
    live_rules._flush()
    assert writes == ["corpus-metrics"]  # a run's first values: at once
    feeding.feed(depot.ingest, source, events[len(events) // 2 :])
    take_queued()
    for _ in range(live.METRICS_EVERY - 1):
        live_rules._flush()
    assert writes == ["corpus-metrics"]  # its distance moved, and nothing else: not yet
    live_rules._flush()
    assert writes == ["corpus-metrics"] * 2
    assert depot.metrics("corpus-metrics")["distance_m"][0] == pytest.approx(expect.expected_distance())
