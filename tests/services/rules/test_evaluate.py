"""A run's events and metrics under rules, from a robot scene logged with the real rerun-sdk: an
`/autonomy/engaged` flag that drops three times, an ambient temperature, a battery on a sequence
timeline, error logs, robots' own events under /events/**, motor currents matched by a glob, and a
path. Every expected value is computed here from the values logged, never by the code under test."""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from services.rules.evaluate import Evaluation, FoundEvent, MetricValue, RunEvaluator, evaluate_messages
from services.rules.spec import RuleSet, parse_rules
from tests.services.rules.recordings import Chunks, chunks, properties, record

pytestmark = pytest.mark.sdk

T0_NS = 1_772_323_200 * 10**9  # 2026-03-01T00:00:00Z
STEP_NS = 500_000_000  # the scene's samples on log_time, every half second
NAN = math.nan
ENGAGED = [0, 1, 1, 0, 0, 1, 1, 0, 1, 1, 1, 0, NAN, 0, 1]  # drops at 3, 7 and 11 (NaN: a gap, skipped)
ENGAGED_CHUNKS = [(0, 4), (4, 9), (9, 15)]  # the drop at 3 spans two chunks
TEMPS = [20, 18, 14, 13, 12, 11, 16, 14, 13, 17, 10, 9, 8, 7, 6, 5, 15, 21, 14, 13, 12, 11]
BATTERY = [30, 25, 19, 18, 17, 16, 22, 19, 18, 21, 15, 14, 13, 12]  # on the `frame` sequence timeline
LOGS = [
    ("INFO", "robot stuck? no, fine"),
    ("ERROR", "Robot STUCK at shelf 4"),
    ("WARN", "path blocked"),
    ("CRITICAL", "motor blocked"),
    ("ERROR", "battery low"),
    ("DEBUG", "stuck in debug"),
]
ROBOT_EVENTS = {  # entity -> (row index on the scene's clock, level, text)
    "/events/hard_brake": [(2, "WARN", "brake at 1.2 g"), (9, "WARN", "brake at 0.9 g")],
    "/events/dock/arrived": [(5, "INFO", "dock 2")],
    "/events/estop": [(12, "CRITICAL", "e-stop pressed")],
}
CURRENTS = {"/motors/left/current": [5, 12, 13, 4, 11], "/motors/right/current": [11, 11, 3, 3, 3]}
rng = np.random.default_rng(7)
PATH = np.cumsum(rng.normal(size=(40, 3)), axis=0)

RULES = """
[[event]]
name = "intervention"
entity = "/autonomy/engaged"
when = "falls_below"
threshold = 0.5
severity = "warn"

[[event]]
name = "disengaged"
entity = "/autonomy/engaged"
when = "below"
threshold = 0.5

[[event]]
name = "cold"
entity = "/sensors/ambient_temp"
when = "below"
threshold = 15
for_s = 1.5

[[event]]
name = "low_battery"
entity = "/battery"
when = "below"
threshold = 20
for_s = 3
timeline = "frame"

[[event]]
name = "stuck"
entity = "/logs"
when = "text"
level = "ERROR"
match = "(?i)stuck|blocked"
severity = "error"

[[event]]
name = "overcurrent"
entity = "/motors/*/current"
when = "above"
threshold = 10

[[metric]]
name = "distance_m"
kind = "path_length"
entity = "/world/robot"

[[metric]]
name = "interventions"
kind = "event_count"
event = "intervention"

[[metric]]
name = "intervention_s"
kind = "duration_s"
event = "intervention"

[[metric]]
name = "hard_brakes"
kind = "event_count"
event = "hard_brake"

[[metric]]
name = "temp_mean"
kind = "mean"
entity = "/sensors/ambient_temp"

[[metric]]
name = "temp_min"
kind = "min"
entity = "/sensors/ambient_temp"

[[metric]]
name = "temp_max"
kind = "max"
entity = "/sensors/ambient_temp"

[[metric]]
name = "temp_last"
kind = "last"
entity = "/sensors/ambient_temp"

[[metric]]
name = "sw_version"
kind = "property"
property = "fleet.sw_version"

[[metric]]
name = "wheel_base"
kind = "property"
property = "fleet.wheel_base"

[[metric]]
name = "no_such_entity"
kind = "mean"
entity = "/nowhere"

[[metric]]
name = "no_such_field"
kind = "property"
property = "fleet.nothing"
"""


def at(i: int) -> int:
    return T0_NS + i * STEP_NS


def times(first: int, last: int) -> np.ndarray:
    return np.array([at(i) for i in range(first, last)], dtype="datetime64[ns]")


def log_scene(rec: rr.RecordingStream) -> None:
    for lo, hi in ENGAGED_CHUNKS:
        scalars = rr.Scalars.columns(scalars=[float(v) for v in ENGAGED[lo:hi]])
        rec.send_columns(
            "/autonomy/engaged", indexes=[rr.TimeColumn("log_time", timestamp=times(lo, hi))], columns=scalars
        )
    half = len(TEMPS) // 2
    for lo, hi in ((0, half), (half, len(TEMPS))):
        scalars = rr.Scalars.columns(scalars=[float(v) for v in TEMPS[lo:hi]])
        rec.send_columns(
            "/sensors/ambient_temp", indexes=[rr.TimeColumn("log_time", timestamp=times(lo, hi))], columns=scalars
        )
    levels, texts = zip(*LOGS, strict=True)
    rec.send_columns(
        "/logs",
        indexes=[rr.TimeColumn("log_time", timestamp=times(0, len(LOGS)))],
        columns=rr.TextLog.columns(text=list(texts), level=list(levels)),
    )
    for entity, rows in ROBOT_EVENTS.items():
        stamps = np.array([at(i) for i, _, _ in rows], dtype="datetime64[ns]")
        columns = rr.TextLog.columns(text=[t for _, _, t in rows], level=[lv for _, lv, _ in rows])
        rec.send_columns(entity, indexes=[rr.TimeColumn("log_time", timestamp=stamps)], columns=columns)
    for entity, values in CURRENTS.items():
        scalars = rr.Scalars.columns(scalars=[float(v) for v in values])
        rec.send_columns(entity, indexes=[rr.TimeColumn("log_time", timestamp=times(0, len(values)))], columns=scalars)
    for i, level in enumerate(BATTERY):  # logged call by call; log_time is the SDK's own clock
        rec.set_time("frame", sequence=i)
        rec.log("/battery", rr.Scalars(float(level)))
    for i, point in enumerate(PATH):
        rec.log("/world/robot", rr.Transform3D(translation=point))
        if i == len(PATH) // 2:
            rec.flush()  # the path in more than one chunk
    rec.log("/camera/image", rr.Scalars(1.0))  # an entity no rule names


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("rules-scene")
    return record(folder / "scene.rrd", log_scene, robot_id="robot-7", sw_version="2.3.1", wheel_base=0.55)


@pytest.fixture(scope="module")
def scene_chunks(scene: Path) -> Chunks:
    return chunks(scene)


@pytest.fixture(scope="module")
def rules() -> RuleSet:
    return parse_rules(RULES)


def evaluate(rules: RuleSet, found: Chunks, scene: Path, max_events: int = 10_000) -> Evaluation:
    return evaluate_messages(rules, found, properties(scene), max_events=max_events)


# --- independent expectations --------------------------------------------------------------------


def expected_ranges(values: Sequence[float], stamps: list[int], holds: Callable[[float], bool], crossing: bool):
    """(start, end) of each maximal range where `holds`, from its first sample to the first sample
    where it no longer does (or the last sample); with `crossing`, only ranges that start after a
    sample where it did not hold. NaN samples are left out first."""
    samples = [(t, v) for t, v in zip(stamps, values, strict=True) if not math.isnan(v)]
    found, start, before = [], None, None
    for t, v in samples:
        now = holds(v)
        if now and start is None and (not crossing or before is False):
            start = t
        if not now and start is not None:
            found.append((start, t))
            start = None
        before = now
    if start is not None:
        found.append((start, samples[-1][0]))
    return found


def long_enough(ranges, minimum):
    return [(s, e) for s, e in ranges if e - s >= minimum]


def of_kind(evaluation: Evaluation, kind: str) -> list[FoundEvent]:
    return [e for e in evaluation.events if e.kind == kind]


def spans(events: list[FoundEvent]) -> list[tuple[int, int]]:
    return sorted((e.start, e.end) for e in events)


def metrics(evaluation: Evaluation) -> dict[str, MetricValue]:
    return {m.name: m for m in evaluation.metrics}


def scene_stamps(values: Sequence[float]) -> list[int]:
    return [at(i) for i in range(len(values))]


# --- the tests -----------------------------------------------------------------------------------


def test_a_flag_that_drops_three_times_gives_three_interventions(rules, scene_chunks, scene):
    evaluation = evaluate(rules, scene_chunks, scene)
    expected = expected_ranges(ENGAGED, scene_stamps(ENGAGED), lambda v: v < 0.5, crossing=True)
    assert expected == [(at(3), at(5)), (at(7), at(8)), (at(11), at(14))]  # the drops, as logged
    interventions = of_kind(evaluation, "intervention")
    assert spans(interventions) == expected
    for event in interventions:
        assert (event.severity, event.timeline, event.timeline_type, event.origin, event.rule) == (
            "warn",
            "log_time",
            "timestamp",
            "rule",
            "intervention",
        )
        assert event.label == "/autonomy/engaged fell below 0.5"
    # `below` also counts the range the flag starts in, which no crossing opened
    below = expected_ranges(ENGAGED, scene_stamps(ENGAGED), lambda v: v < 0.5, crossing=False)
    assert spans(of_kind(evaluation, "disengaged")) == below and below[0] == (at(0), at(1))
    assert evaluation.in_order and not evaluation.capped and evaluation.note is None


def test_below_keeps_the_ranges_that_last_for_s(rules, scene_chunks, scene):
    evaluation = evaluate(rules, scene_chunks, scene)
    every = expected_ranges(TEMPS, scene_stamps(TEMPS), lambda v: v < 15, crossing=False)
    expected = long_enough(every, 1.5e9)
    assert len(every) > len(expected) >= 2  # some ranges too short, one open at the end kept
    assert expected[-1][1] == at(len(TEMPS) - 1)
    assert spans(of_kind(evaluation, "cold")) == expected


def test_for_s_counts_ticks_on_a_sequence_timeline(rules, scene_chunks, scene):
    evaluation = evaluate(rules, scene_chunks, scene)
    every = expected_ranges(BATTERY, list(range(len(BATTERY))), lambda v: v < 20, crossing=False)
    expected = long_enough(every, 3)
    assert expected and len(every) > len(expected)
    low = of_kind(evaluation, "low_battery")
    assert spans(low) == expected
    assert {(e.timeline, e.timeline_type) for e in low} == {("frame", "sequence")}


def test_text_events_match_level_and_regex(rules, scene_chunks, scene):
    evaluation = evaluate(rules, scene_chunks, scene)
    order = ["TRACE", "DEBUG", "INFO", "WARN", "ERROR", "CRITICAL"]
    expected = [
        (at(i), at(i), text)
        for i, (level, text) in enumerate(LOGS)
        if order.index(level) >= order.index("ERROR") and re.search("(?i)stuck|blocked", text)
    ]
    assert len(expected) == 2
    stuck = of_kind(evaluation, "stuck")
    assert sorted((e.start, e.end, e.label) for e in stuck) == expected
    assert {(e.severity, e.origin) for e in stuck} == {("error", "rule")}


def test_robots_make_events_under_events_with_no_rule(rules, scene_chunks, scene):
    evaluation = evaluate(rules, scene_chunks, scene)
    severity = {"INFO": "info", "WARN": "warn", "ERROR": "error", "CRITICAL": "error"}
    expected = sorted(
        (entity.removeprefix("/events/"), severity[level], at(i), text)
        for entity, rows in ROBOT_EVENTS.items()
        for i, level, text in rows
    )
    robot = [e for e in evaluation.events if e.origin == "robot"]
    assert sorted((e.kind, e.severity, e.start, e.label) for e in robot) == expected
    assert all(e.start == e.end and e.rule is None and e.timeline == "log_time" for e in robot)
    assert {e.kind for e in robot} == {"hard_brake", "dock/arrived", "estop"}


def test_a_glob_rule_evaluates_each_entity_on_its_own(rules, scene_chunks, scene):
    evaluation = evaluate(rules, scene_chunks, scene)
    found = of_kind(evaluation, "overcurrent")
    for entity, values in CURRENTS.items():
        expected = expected_ranges(values, scene_stamps(values), lambda v: v > 10, crossing=False)
        assert spans([e for e in found if e.label.startswith(entity + " ")]) == expected
    assert len(found) == 3  # left: 1-3 and 4 (open at its end); right: 0-2


def test_metrics(rules, scene_chunks, scene):
    values = metrics(evaluate(rules, scene_chunks, scene))
    logged = PATH.astype(np.float32).astype(np.float64)  # Transform3D holds float32 translations
    distance = float(np.sum(np.sqrt(np.sum((logged[1:] - logged[:-1]) ** 2, axis=1))))
    assert values["distance_m"].value == pytest.approx(distance, rel=1e-9)
    drops = expected_ranges(ENGAGED, scene_stamps(ENGAGED), lambda v: v < 0.5, crossing=True)
    assert values["interventions"] == MetricValue("interventions", 3.0, None)
    assert values["intervention_s"].value == pytest.approx(sum(e - s for s, e in drops) / 1e9)
    assert values["hard_brakes"].value == len(ROBOT_EVENTS["/events/hard_brake"])
    assert values["temp_mean"].value == pytest.approx(float(np.mean(TEMPS)))
    assert (values["temp_min"].value, values["temp_max"].value, values["temp_last"].value) == (
        min(TEMPS),
        max(TEMPS),
        TEMPS[-1],
    )
    assert values["sw_version"] == MetricValue("sw_version", None, "2.3.1")
    assert values["wheel_base"] == MetricValue("wheel_base", 0.55, None)
    assert "no_such_entity" not in values and "no_such_field" not in values  # no data: no metric
    assert list(values) == [m.name for m in rules.metrics if m.name in values]  # the rules' order


def test_live_evaluation_gives_closed_events_as_they_come_and_the_same_result(rules, scene_chunks, scene):
    stored = evaluate(rules, scene_chunks, scene)
    live = RunEvaluator(rules, max_events=10_000)
    taken: list[FoundEvent] = []
    for msg, meta in scene_chunks:
        live.add(msg, meta)
        taken += live.take_closed()
    assert live.take_closed() == []  # each event is taken once
    result = live.finish(properties(scene))
    assert result == stored
    assert set(taken) < set(result.events)  # what was still open came at the end
    open_at_end = set(result.events) - set(taken)
    assert (at(len(TEMPS) - 1)) in {e.end for e in open_at_end}


def test_chunks_out_of_time_order_make_the_live_result_not_in_order(rules, scene_chunks, scene):
    engaged = [i for i, (_, meta) in enumerate(scene_chunks) if meta.entity_path == "/autonomy/engaged"]
    assert len(engaged) == len(ENGAGED_CHUNKS)
    shuffled = list(scene_chunks)
    shuffled[engaged[0]], shuffled[engaged[-1]] = shuffled[engaged[-1]], shuffled[engaged[0]]
    live = RunEvaluator(rules, max_events=10_000)
    for msg, meta in shuffled:
        live.add(msg, meta)
    assert not live.finish(properties(scene)).in_order
    # a stored run is evaluated exactly whatever the order of its chunks
    assert evaluate(rules, shuffled, scene) == evaluate(rules, scene_chunks, scene)
    # chunks of unrelated entities in any order do not matter
    in_order = RunEvaluator(rules, max_events=10_000)
    for msg, meta in sorted(scene_chunks, key=lambda c: c[1].entity_path):
        in_order.add(msg, meta)
    assert in_order.finish(properties(scene)).in_order


def test_events_stop_at_the_cap_and_say_so(rules, scene_chunks, scene):
    everything = evaluate(rules, scene_chunks, scene)
    capped = evaluate(rules, scene_chunks, scene, max_events=5)
    assert len(everything.events) > 5 and len(capped.events) == 5
    assert capped.capped and not everything.capped
    assert capped.note is not None and "cap of 5 events" in capped.note
    kept = {(e.kind, e.start, e.end, e.label) for e in capped.events}
    lost = [e for e in everything.events if (e.kind, e.start, e.end, e.label) not in kept]
    for who in {f"rule {e.rule}" if e.rule else f"robot events {e.kind}" for e in lost}:
        assert who in capped.note
    assert metrics(capped)["interventions"].value == 3  # metrics count every event found


def test_only_named_entities_and_robot_events_are_wanted(rules, scene_chunks):
    live = RunEvaluator(rules, max_events=10)
    wanted = {meta.entity_path for _, meta in scene_chunks if live.wants(meta.entity_path)}
    assert "/camera/image" not in wanted
    assert {"/autonomy/engaged", "/motors/left/current", "/events/estop", "/events/dock/arrived"} <= wanted
    assert not live.wants("/events") and not live.wants("/motors/left/current/raw")


def test_no_rules_find_only_robot_events(scene_chunks, scene):
    evaluation = evaluate(RuleSet.empty(), scene_chunks, scene)
    assert evaluation.metrics == []
    assert {e.origin for e in evaluation.events} == {"robot"}
    assert len(evaluation.events) == sum(len(rows) for rows in ROBOT_EVENTS.values())


@pytest.mark.parametrize("batch", [1, 3, 7, 10_000])
def test_chunks_added_in_batches_give_what_chunks_added_one_by_one_give(rules, scene_chunks, scene, batch):
    one_by_one = RunEvaluator(rules, max_events=10_000)
    for msg, meta in scene_chunks:
        one_by_one.add(msg, meta)
    batched = RunEvaluator(rules, max_events=10_000)
    taken: list[FoundEvent] = []
    for start in range(0, len(scene_chunks), batch):
        batched.add_many(scene_chunks[start : start + batch])
        taken += batched.take_closed()
    result = batched.finish(properties(scene))
    assert result == one_by_one.finish(properties(scene)) == evaluate(rules, scene_chunks, scene)
    assert set(taken) <= set(result.events)


def test_one_entitys_consecutive_scalar_chunks_are_evaluated_as_one(rules, scene_chunks, scene, monkeypatch):
    by_entity = sorted(scene_chunks, key=lambda c: c[1].entity_path)  # each entity's chunks together, in order
    calls: list[int] = []
    numeric = RunEvaluator._numeric

    def counted(self: RunEvaluator, path: str, found: list[object], values: np.ndarray, index: object) -> None:
        calls.append(len(values))
        numeric(self, path, found, values, index)  # type: ignore[arg-type]

    monkeypatch.setattr(RunEvaluator, "_numeric", counted)
    batched = RunEvaluator(rules, max_events=10_000)
    batched.add_many(by_entity)
    assert batched.finish(properties(scene)) == evaluate(rules, scene_chunks, scene)
    engaged = [meta for _, meta in scene_chunks if meta.entity_path == "/autonomy/engaged"]
    assert len(engaged) > 1 and sum(meta.num_rows for meta in engaged) in calls  # its chunks in one call
