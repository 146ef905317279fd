"""A small corpus written as the corpus writes it (catalog/corpus.py): runs with metrics (numbers
and a text one), tags from people and robots, events of rules, robots and people. The runs, REST,
SQL and catalog-protocol tests of search all read this one scene, so they can agree on it."""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from sqlalchemy.orm import Session

from catalog import corpus, queries
from catalog.corpus import EventFacts, MetricFacts
from tests.catalog.records import run_record

T0 = dt.datetime(2026, 11, 1, 8, 0, tzinfo=dt.UTC)
NS = 10**9
APP = "nav"
RULES_VERSION = 3


@dataclass(frozen=True)
class SceneRun:
    run_id: str
    robot: str
    hours: int  # started T0 + hours
    metrics: dict[str, float | str]
    tags: dict[str, str]  # tag -> who added it
    events: tuple[tuple[str, str], ...]  # (kind, origin)


RUNS = (
    SceneRun(
        "r-1",
        "robot-a",
        0,
        {"distance_m": 150.0, "sw_version": "2.3"},
        {"night-shift": "alice", "dock-2": "robot"},
        (("intervention", "rule"), ("intervention", "rule")),
    ),
    SceneRun(
        "r-2",
        "robot-a",
        1,
        {"distance_m": 80.0, "sw_version": "2.4"},
        {"night-shift": "robot"},
        (("hard_brake", "robot"),),
    ),
    SceneRun(
        "r-3", "robot-b", 2, {"distance_m": 100.0, "sw_version": "2.3", "temp_c": -3.5}, {}, (("intervention", "rule"),)
    ),
    SceneRun("r-4", "robot-b", 3, {"distance_m": 150.0}, {"dock-2": "bob"}, ()),
    SceneRun("r-5", "robot-a", 4, {}, {"night-shift": "alice"}, (("intervention", "person"),)),
    SceneRun("r-6", "robot-b", 5, {"temp_c": 21.0}, {}, (("hard_brake", "robot"), ("stuck", "rule"))),
)
IDS = [run.run_id for run in RUNS]


def write_scene(session: Session, application: str = APP) -> None:
    """The runs (as ingest files them) and their corpus (as an evaluation, tagging and annotating do)."""
    for run in RUNS:
        start = T0 + dt.timedelta(hours=run.hours)
        queries.save_run(
            session,
            run_record(run.run_id, start, robot_id=run.robot, application_id=application, ended_at=None),
            start,
        )
        write_corpus(session, run, start)
    session.flush()


def write_corpus(session: Session, run: SceneRun, at: dt.datetime) -> None:
    made = [event(kind, origin, i) for i, (kind, origin) in enumerate(run.events) if origin != "person"]
    corpus.replace_evaluation(
        session,
        run_id=run.run_id,
        robot_id=run.robot,
        rules_version=RULES_VERSION,
        state="final",
        events=made,
        metrics=[
            MetricFacts(name, None, value) if isinstance(value, str) else MetricFacts(name, value, None)
            for name, value in run.metrics.items()
        ],
        capped=run.run_id == "r-6",
        note="rule stuck stopped at 1 event" if run.run_id == "r-6" else None,
        now=at,
    )
    for i, (kind, origin) in enumerate(run.events):
        if origin == "person":
            corpus.add_event(session, run.run_id, run.robot, event(kind, origin, i), at, f"ev-person{i:011d}")
    for tag, who in run.tags.items():
        corpus.add_tags(session, run.run_id, [tag], who, at)


def event(kind: str, origin: str, i: int) -> EventFacts:
    source = {"rule": f"rule {kind}@{RULES_VERSION}", "robot": "robot", "person": "alice"}[origin]
    start = (1_790_000_000 + 10 * i) * NS
    return EventFacts(kind, "warn", "log_time", "timestamp", start, start + 2 * NS, origin, source, f"{kind} {i}")


def expected(flt: Mapping[str, Sequence[str]]) -> list[str]:
    """The scene's runs a filter keeps, computed from the scene itself (in id order)."""
    kept = []
    for run in RUNS:
        ok = True
        for expression in flt.get("metric", ()):
            ok &= _meets(run, expression)
        for tag in flt.get("tag", ()):
            ok &= tag in run.tags
        for kind in flt.get("event", ()):
            ok &= any(k == kind for k, _ in run.events)
        if ok:
            kept.append(run.run_id)
    return kept


def _meets(run: SceneRun, expression: str) -> bool:
    for op in (">=", "<=", "!=", ">", "<", "="):
        name, sep, text = expression.partition(op)
        if sep:
            break
    if name not in run.metrics:
        return False
    value = run.metrics[name]
    if isinstance(value, str):
        return {"=": value == text, "!=": value != text}.get(op, False)
    number = float(text)
    return {
        ">": value > number,
        ">=": value >= number,
        "<": value < number,
        "<=": value <= number,
        "=": value == number,
        "!=": value != number,
    }[op]
