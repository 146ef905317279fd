"""A dataset's columns counted as its runs are written (catalog/dataset_columns.py), on DuckDB and
Postgres: what the writers count equals what counting the runs again gives, each run once, and a
dataset's segment table schema is read from them."""

from __future__ import annotations

import datetime as dt
from typing import Any

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus, queries
from catalog.dataset_columns import PROPERTIES_ENTITY, apply_pending, dataset_columns, refill
from catalog.db import session_scope
from catalog.models import DatasetColumn
from catalog.queries import EntityRecord, TimelineRecord
from services.rrd import manifest
from tests.catalog.records import run_record

NOW = dt.datetime(2026, 11, 30, 12, 0, tzinfo=dt.UTC)


def counted(session: Session) -> dict[tuple[str, str, str, str], int]:
    rows = session.execute(
        sa.select(
            DatasetColumn.application_id,
            DatasetColumn.kind,
            DatasetColumn.name,
            DatasetColumn.detail,
            DatasetColumn.runs,
        )
    )
    return {(app, kind, name, detail): runs for app, kind, name, detail, runs in rows}


def entity(path: str, *archetypes: str) -> EntityRecord:
    return EntityRecord(path, 1, 0, 1, 10, list(archetypes), [])


def save(session: Session, run_id: str, application: str = "nav", **changes: Any) -> None:
    queries.save_run(session, run_record(run_id, application_id=application, **changes), NOW)
    session.flush()


def metrics(run_id: str, *values: tuple[str, float | None, str | None]) -> corpus.EvaluationFacts:
    return corpus.EvaluationFacts(
        run_id=run_id,
        robot_id="robot-7",
        rules_version=1,
        state="final",
        events=(),
        metrics=tuple(corpus.MetricFacts(name, value, text) for name, value, text in values),
        capped=False,
        note=None,
    )


def fill(session: Session) -> None:
    """Runs of two datasets, written again as live runs are (each flush), with metrics replaced."""
    location = entity(f"{PROPERTIES_ENTITY}/location", "rerun.archetypes.GeoPoints")
    for flush in range(3):  # the same items each time: counted once
        save(
            session,
            "run-1",
            properties={"fleet": {"site": "a", "n": flush}, "recording": {"RecordingInfo:name": "x"}},
            entities=[location, entity("/world", "rerun.archetypes.Points3D")],
            timelines=[TimelineRecord("t", "sequence", 0, flush), TimelineRecord("log_time", "timestamp", 1, 2)],
        )
    save(
        session,
        "run-2",
        properties={"fleet": {"site": ["b", "c"], "score": 1.5}},
        timelines=[TimelineRecord("t", "duration", 0, 1)],
    )
    save(session, "run-3", properties={"fleet": {"empty": []}}, timelines=[TimelineRecord("t", "duration", 0, 1)])
    save(session, "run-4", "arm", properties={"fleet": {"site": True}}, entities=[location])
    corpus.replace_evaluations(
        session, [metrics("run-1", ("distance_m", 3.0, None)), metrics("run-2", ("sw", None, "2.3"))], NOW
    )
    corpus.replace_evaluations(session, [metrics("run-1", ("distance_m", 4.0, None), ("stops", 2.0, None))], NOW)
    apply_pending(session)  # as the transaction's commit would


def test_what_the_writers_count_is_what_counting_the_runs_again_gives(session: Session):
    fill(session)
    written = counted(session)
    assert written[("nav", "timeline", "t", "duration")] == 2
    assert written[("nav", "property", '["fleet", "site"]', "str")] == 2  # run-2's two values: one run
    assert written[("nav", "metric", "distance_m", "number")] == 1  # its value replaced: the same run
    assert refill(session) == 4
    assert counted(session) == written


def test_a_datasets_columns_are_what_its_runs_hold(session: Session):
    fill(session)
    nav = dataset_columns(session, "nav")
    assert nav.properties == {
        ("fleet", "site"): {"str"},
        ("fleet", "n"): {"int"},
        ("fleet", "score"): {"float"},
        ("fleet", "empty"): set(),  # a column of no kind of value yet
        ("recording", "RecordingInfo:name"): {"str"},
    }
    assert nav.archetypes == {f"{PROPERTIES_ENTITY}/location": {"rerun.archetypes.GeoPoints"}}  # property entities only
    assert nav.timelines == {"t": "duration", "log_time": "timestamp"}  # the type most runs log it with
    assert nav.metrics == {"distance_m": False, "stops": False, "sw": True}
    arm = dataset_columns(session, "arm")
    assert arm.properties == {("fleet", "site"): {"bool"}} and arm.timelines == {} and arm.metrics == {}
    assert dataset_columns(session, "nobody").properties == {}


def test_a_column_goes_when_no_run_of_the_dataset_holds_it(session: Session):
    save(session, "run-1", properties={"fleet": {"site": 3}})
    save(session, "run-2", properties={"fleet": {"site": 4, "dock": "d2"}})
    save(session, "run-1", properties={"fleet": {"site": "three"}})  # a live run's property changed
    assert dataset_columns(session, "nav").properties == {("fleet", "site"): {"int", "str"}, ("fleet", "dock"): {"str"}}
    save(session, "run-2", "arm", properties={"fleet": {"site": 4, "dock": "d2"}})  # its application changed
    assert dataset_columns(session, "nav").properties == {("fleet", "site"): {"str"}}
    assert dataset_columns(session, "arm").properties == {("fleet", "site"): {"int"}, ("fleet", "dock"): {"str"}}
    assert queries.mark_deleted(session, "run-2", NOW) and not queries.mark_deleted(session, "run-2", NOW)
    assert dataset_columns(session, "arm").properties == {}  # (reading applies what is pending)
    written = counted(session)
    refill(session)
    assert counted(session) == written


def test_metrics_move_with_their_run_and_go_with_it(session: Session):
    save(session, "run-1")
    corpus.replace_evaluations(session, [metrics("run-1", ("distance_m", 3.0, None), ("sw", None, "2.3"))], NOW)
    corpus.replace_evaluations(session, [metrics("run-1", ("distance_m", 4.0, None))], NOW)
    assert dataset_columns(session, "nav").metrics == {"distance_m": False}
    save(session, "run-1", "arm")
    assert dataset_columns(session, "nav").metrics == {} and dataset_columns(session, "arm").metrics == {
        "distance_m": False
    }
    save(session, "run-2", "arm")
    queries.remove_hot_run(session, "run-1")  # ingest dropped it
    assert dataset_columns(session, "arm").metrics == {}
    assert counted(session) == {}


def test_the_property_entity_is_the_one_the_recordings_use():
    assert PROPERTIES_ENTITY == manifest.PROPERTIES_ENTITY


def test_a_scrubbed_property_leaves_the_columns(session: Session):
    save(session, "run-1", properties={"fleet": {"site": "a", "token": "s3cr3t"}})
    run = queries.require_run(session, "run-1")
    queries.replace_properties(session, run, {"fleet": {"site": "a"}})
    assert dataset_columns(session, "nav").properties == {("fleet", "site"): {"str"}}


def test_counts_are_written_as_the_transaction_commits_and_dropped_with_a_rollback(
    catalog: sessionmaker[Session],
):
    with session_scope(catalog, write=True) as session:
        save(session, "run-1", timelines=[TimelineRecord("t", "sequence", 0, 1)])
        assert counted(session) == {}  # held by the session until it commits
    with session_scope(catalog) as session:
        assert counted(session) == {("nav", "timeline", "t", "sequence"): 1}
    with pytest.raises(RuntimeError), session_scope(catalog, write=True) as session:
        save(session, "run-2", timelines=[TimelineRecord("u", "sequence", 0, 1)])
        raise RuntimeError("the writer fails")
    with session_scope(catalog, write=True) as session:
        save(session, "run-3")  # a later transaction on the same connection pool: nothing of run-2's
    with session_scope(catalog) as session:
        assert counted(session) == {("nav", "timeline", "t", "sequence"): 1}


def test_a_name_too_long_for_an_index_key_is_no_column(session: Session):
    long = "x" * 3000  # over what a Postgres index key holds
    save(
        session,
        "run-1",
        properties={"fleet": {long: 1, "site": "a"}},
        timelines=[TimelineRecord(long, "sequence", 0, 1), TimelineRecord("t", "sequence", 0, 1)],
    )
    assert dataset_columns(session, "nav").properties == {("fleet", "site"): {"str"}}
    assert dataset_columns(session, "nav").timelines == {"t": "sequence"}
    written = counted(session)
    refill(session)
    assert counted(session) == written
