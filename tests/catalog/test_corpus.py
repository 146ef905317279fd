"""The corpus's catalog rows: rules versions, a run's evaluation replaced whole, people's events
and tags left alone by it."""

from __future__ import annotations

import datetime as dt

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus
from catalog.corpus import EventFacts, MetricFacts
from catalog.db import session_scope
from core.clock import aware

NOW = dt.datetime(2026, 11, 29, 12, tzinfo=dt.UTC)


def _rule_event(start: int, kind: str = "intervention") -> EventFacts:
    return EventFacts(kind, "warn", "log_time", "timestamp", start, start + 10, "rule", f"rule {kind}@1")


def _replace(session: Session, version: int, events: list[EventFacts], metrics: list[MetricFacts]) -> list[str]:
    new = corpus.replace_evaluation(
        session,
        run_id="run-1",
        robot_id="r1",
        rules_version=version,
        state="final",
        events=events,
        metrics=metrics,
        capped=False,
        note=None,
        now=NOW,
    )
    return sorted(e.id for e in new)


def test_same_text_makes_no_new_version(catalog: sessionmaker[Session]) -> None:
    with session_scope(catalog, write=True) as session:
        first, made = corpus.add_rules_version(session, "[[event]]\n", "alice", NOW)
        assert (first.version, made) == (1, True)
        again, made = corpus.add_rules_version(session, "[[event]]\n", "bob", NOW)
        assert (again.version, made) == (1, False)
        second, made = corpus.add_rules_version(session, "[[metric]]\n", "bob", NOW)
        assert (second.version, made) == (2, True)
    with session_scope(catalog) as session:
        assert [v.version for v in corpus.rules_history(session)] == [2, 1]
        assert corpus.current_rules(session).created_by == "bob"  # type: ignore[union-attr]


def test_replacing_an_evaluation_never_doubles_and_spares_people(catalog: sessionmaker[Session]) -> None:
    with session_scope(catalog, write=True) as session:
        new = _replace(session, 1, [_rule_event(100), _rule_event(200)], [MetricFacts("distance_m", 3.5, None)])
        assert len(new) == 2
        person = EventFacts("note", "info", "log_time", "timestamp", 5, 6, "person", "alice", label="look")
        corpus.add_event(session, "run-1", "r1", person, NOW, "ev-person000000001")
        corpus.add_tags(session, "run-1", ["night", "dock-2", "night"], "alice", NOW)
    with session_scope(catalog, write=True) as session:
        # The same events found again, one more, and a metric changed: only the new one is new.
        new = _replace(
            session, 2, [_rule_event(100), _rule_event(200), _rule_event(300)], [MetricFacts("distance_m", 4.0, None)]
        )
        assert len(new) == 1
    with session_scope(catalog) as session:
        events = corpus.events_of_run(session, "run-1")
        assert [(e.origin, e.range_start) for e in events] == [
            ("person", 5),
            ("rule", 100),
            ("rule", 200),
            ("rule", 300),
        ]
        assert {e.rules_version for e in events if e.origin == "rule"} == {2}
        assert [(m.name, m.value, m.rules_version) for m in corpus.metrics_of(session, "run-1")] == [
            ("distance_m", 4.0, 2)
        ]
        assert corpus.event_counts_of(session, "run-1") == {"intervention": 3, "note": 1}
        assert [t.tag for t in corpus.tags_of(session, "run-1")] == ["dock-2", "night"]
        evaluation = corpus.evaluation_of(session, "run-1")
        assert evaluation is not None and (evaluation.rules_version, evaluation.state) == (2, "final")


def test_robot_tags_follow_the_property_and_leave_peoples(catalog: sessionmaker[Session]) -> None:
    with session_scope(catalog, write=True) as session:
        corpus.add_tags(session, "run-1", ["dock-2"], "alice", NOW)
        corpus.sync_robot_tags(session, "run-1", ["night", "dock-2"], NOW)
    with session_scope(catalog, write=True) as session:
        assert {(t.tag, t.added_by) for t in corpus.tags_of(session, "run-1")} == {
            ("dock-2", "alice"),
            ("night", "robot"),
        }
        corpus.sync_robot_tags(session, "run-1", [], NOW)
    with session_scope(catalog) as session:
        assert [(t.tag, t.added_by) for t in corpus.tags_of(session, "run-1")] == [("dock-2", "alice")]


def test_replacing_writes_only_what_differs_and_keeps_when_an_event_was_first_recorded(
    catalog: sessionmaker[Session],
) -> None:
    later = NOW + dt.timedelta(minutes=5)
    with session_scope(catalog, write=True) as session:
        _replace(
            session, 1, [_rule_event(100), _rule_event(200)], [MetricFacts("a", 1.0, None), MetricFacts("b", 2.0, None)]
        )
    with session_scope(catalog, write=True) as session:
        new = corpus.replace_evaluation(
            session,
            run_id="run-1",
            robot_id="r1",
            rules_version=1,
            state="live",
            events=[_rule_event(200), _rule_event(300)],  # 100 no longer found, 300 new
            metrics=[MetricFacts("a", 1.0, None), MetricFacts("c", 3.0, None)],  # b gone, c new
            capped=False,
            note=None,
            now=later,
        )
        assert [e.range_start for e in new] == [300]
    with session_scope(catalog) as session:
        events = {e.range_start: e.created_at for e in corpus.events_of_run(session, "run-1")}
        assert sorted(events) == [200, 300]
        assert aware(events[200]) == NOW and aware(events[300]) == later  # recorded when first found
        metrics = {m.name: (m.value, aware(m.computed_at)) for m in corpus.metrics_of(session, "run-1")}
        assert metrics == {"a": (1.0, NOW), "c": (3.0, later)}  # an unchanged value is not written again


def test_several_runs_replaced_at_once_each_keep_their_own(catalog: sessionmaker[Session]) -> None:
    def facts(run_id: str, starts: list[int], value: float) -> corpus.EvaluationFacts:
        events = [_rule_event(s) for s in starts]
        return corpus.EvaluationFacts(run_id, "r1", 1, "live", events, [MetricFacts("a", value, None)], False, None)

    with session_scope(catalog, write=True) as session:
        new = corpus.replace_evaluations(session, [facts("run-1", [100], 1.0), facts("run-2", [100, 200], 2.0)], NOW)
        assert sorted((e.run_id, e.range_start) for e in new) == [("run-1", 100), ("run-2", 100), ("run-2", 200)]
    with session_scope(catalog, write=True) as session:
        # run-1 finds one more; run-2 loses one: neither touches the other's rows.
        new = corpus.replace_evaluations(session, [facts("run-1", [100, 300], 1.5), facts("run-2", [200], 2.0)], NOW)
        assert [(e.run_id, e.range_start) for e in new] == [("run-1", 300)]
    with session_scope(catalog) as session:
        assert [e.range_start for e in corpus.events_of_run(session, "run-1")] == [100, 300]
        assert [e.range_start for e in corpus.events_of_run(session, "run-2")] == [200]
        assert [m.value for m in corpus.metrics_of(session, "run-1")] == [1.5]
        assert [m.value for m in corpus.metrics_of(session, "run-2")] == [2.0]
        assert {corpus.evaluation_of(session, r).state for r in ("run-1", "run-2")} == {"live"}  # type: ignore[union-attr]
    with session_scope(catalog, write=True) as session, pytest.raises(ValueError, match="one evaluation per run"):
        corpus.replace_evaluations(session, [facts("run-1", [], 0.0), facts("run-1", [], 0.0)], NOW)
