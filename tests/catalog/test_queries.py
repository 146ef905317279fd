"""Catalog writes and reads, identical on DuckDB and Postgres."""

from __future__ import annotations

import datetime as dt
import json
import re

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog import queries
from catalog.models import Dataset
from catalog.queries import EntityRecord, RunRecord, TimelineRecord
from core.clock import aware
from tests.catalog.records import run_record

NOW = dt.datetime(2026, 11, 21, 12, 0, tzinfo=dt.UTC)


def _record(**changes: object) -> RunRecord:
    live = {
        "status": "live",
        "started_at": NOW - dt.timedelta(minutes=5),
        "ended_at": None,
        "chunks": 10,
        "rows": 100,
        "bytes": 12345,
        "properties": {"fleet": {"robot_id": "robot-7"}},
        "entities": [
            EntityRecord("/world/points", 6, 0, 60, 10000, ["rerun.archetypes.Points3D"], ["Points3D:positions"]),
            EntityRecord("/__properties/fleet", 1, 1, 1, 345, [], ["robot_id"]),
        ],
        "timelines": [
            TimelineRecord("frame", "sequence", 0, 59),
            TimelineRecord("log_time", "timestamp", 1_700_000_000 * 10**9, 1_700_000_060 * 10**9),
        ],
    }
    return run_record("run-1", NOW, **{**live, **changes})


def test_save_and_read_back(session: Session):
    queries.save_run(session, _record(), NOW)
    session.flush()
    run = queries.get_run(session, "run-1")
    assert run is not None
    assert (run.robot_id, run.application_id, run.status, run.tier) == ("robot-7", "nav", "live", "hot")
    assert (run.chunks, run.rows, run.bytes, run.sdk_version) == (10, 100, 12345, "0.41.0")
    assert run.date == dt.date(2026, 11, 21)
    assert json.loads(run.properties) == {"fleet": {"robot_id": "robot-7"}}
    assert [e.path for e in queries.run_entities(session, "run-1")] == ["/__properties/fleet", "/world/points"]
    points = queries.run_entities(session, "run-1")[1]
    assert (points.chunks, points.rows, json.loads(points.archetypes)) == (6, 60, ["rerun.archetypes.Points3D"])
    timelines = {t.name: (t.type, t.min, t.max) for t in queries.run_timelines(session, "run-1")}
    assert timelines == {
        "frame": ("sequence", 0, 59),
        "log_time": ("timestamp", 1_700_000_000 * 10**9, 1_700_000_060 * 10**9),
    }
    assert [r.id for r in queries.list_robots(session)] == ["robot-7"]


def test_save_again_replaces_entities_and_timelines(session: Session):
    queries.save_run(session, _record(), NOW)
    later = NOW + dt.timedelta(minutes=1)
    queries.save_run(
        session,
        _record(
            chunks=11,
            last_data_at=later,
            entities=[EntityRecord("/robot/speed", 1, 0, 1, 50, [], ["Scalars:scalars"])],
            timelines=[TimelineRecord("frame", "sequence", 0, 60)],
        ),
        later,
    )
    session.flush()
    run = queries.get_run(session, "run-1")
    assert run is not None and run.chunks == 11
    assert [e.path for e in queries.run_entities(session, "run-1")] == ["/robot/speed"]
    assert [(t.name, t.max) for t in queries.run_timelines(session, "run-1")] == [("frame", 60)]
    robot = queries.list_robots(session)[0]
    assert aware(robot.last_seen_at) == later  # timestamps come back as the same instant


def test_unknown_run_is_none(session: Session):
    assert queries.get_run(session, "nope") is None
    assert queries.run_entities(session, "nope") == []


# --- datasets: one per application id, made with its first run --------------------------------


def _dataset(session: Session, name: str) -> Dataset:
    found = session.get(Dataset, name)
    assert found is not None, f"no dataset {name!r}"
    return found


def test_an_applications_first_run_makes_its_dataset_with_a_tuid(session: Session):
    queries.save_run(session, _record(), NOW)
    session.flush()
    dataset = _dataset(session, "nav")
    assert re.fullmatch(r"[0-9A-F]{16}[0-9a-f]{16}", dataset.entry_id), dataset.entry_id
    assert int(dataset.entry_id[:16], 16) == int(NOW.timestamp()) * 10**9  # a TUID: its time first
    assert (aware(dataset.created_at), aware(dataset.updated_at)) == (NOW, NOW)
    assert queries.dataset_entry_id(session, "nav") == dataset.entry_id
    assert [d.name for d in queries.datasets(session)] == ["nav"]


def test_a_dataset_keeps_its_entry_id_while_its_runs_are_saved_and_added(session: Session):
    queries.save_run(session, _record(), NOW)
    first = _dataset(session, "nav").entry_id
    later, latest = NOW + dt.timedelta(minutes=1), NOW + dt.timedelta(minutes=2)
    queries.save_run(session, _record(chunks=20, status="closed"), later)  # the same run again
    session.flush()
    assert (_dataset(session, "nav").entry_id, aware(_dataset(session, "nav").updated_at)) == (first, NOW)
    queries.save_run(session, _record(id="run-2"), latest)  # another run of the application
    session.flush()
    dataset = _dataset(session, "nav")
    assert (dataset.entry_id, aware(dataset.created_at), aware(dataset.updated_at)) == (first, NOW, latest)


def test_each_application_has_its_own_dataset_and_a_run_without_one_makes_none(session: Session):
    queries.save_run(session, _record(), NOW)
    queries.save_run(session, _record(id="run-2", application_id="arm"), NOW)
    queries.save_run(session, _record(id="run-3", application_id=""), NOW)
    session.flush()
    found = {d.name: d.entry_id for d in queries.datasets(session)}
    assert sorted(found) == ["arm", "nav"]
    assert found["arm"] != found["nav"]  # made at the same instant, told apart by their names
    assert queries.dataset_entry_id(session, "") is None
    assert queries.dataset_entry_id(session, "unknown") is None


def test_ensure_dataset_restores_a_given_entry_id_but_never_replaces_one(session: Session):
    kept = "18EA6CA8C3020B3029d1569232672548"
    restored = queries.ensure_dataset(session, "nav", NOW, kept)
    assert restored.entry_id == kept
    again = queries.ensure_dataset(session, "nav", NOW + dt.timedelta(days=1), "18EA6CA8C3020B30ffffffffffffffff")
    assert again.entry_id == kept
    queries.save_run(session, _record(), NOW + dt.timedelta(days=2))  # its first run, after a rebuild made it
    session.flush()
    assert queries.dataset_entry_id(session, "nav") == kept


def test_entities_and_timelines_keep_every_value_on_both_catalogs(session: Session):
    # On DuckDB these rows go in as one Arrow table (`insert_rows`), elsewhere by executemany: the
    # same values must come back either way, at the edges of their types.
    big = 2**63 - 1
    entities = [EntityRecord(f"/wörld/点/{i}", big - i, i, big, 0, ['a"b', "c'd"], ["é:comp"]) for i in range(300)] + [
        EntityRecord("/empty", 0, 0, 0, 0, [], [])
    ]
    timelines = [TimelineRecord("neg", "duration", -(2**63), big), TimelineRecord("t ö", "timestamp", 0, 0)]
    queries.save_run(session, _record(entities=entities, timelines=timelines), NOW)
    session.flush()
    got = {e.path: e for e in queries.run_entities(session, "run-1")}
    assert len(got) == 301
    first = got["/wörld/点/0"]
    assert (first.chunks, first.static_chunks, first.rows, first.bytes) == (big, 0, big, 0)
    assert json.loads(first.archetypes) == ['a"b', "c'd"] and json.loads(first.components) == ["é:comp"]
    assert got["/wörld/点/299"].chunks == big - 299 and json.loads(got["/empty"].archetypes) == []
    back = {t.name: (t.type, t.min, t.max) for t in queries.run_timelines(session, "run-1")}
    assert back == {"neg": ("duration", -(2**63), big), "t ö": ("timestamp", 0, 0)}


def test_a_row_the_catalog_refuses_is_its_error_on_both_catalogs(session: Session):
    # Two entities with one path break the primary key: SQLAlchemy's IntegrityError either way (on
    # DuckDB the rows go in as an Arrow table, through the session's connection all the same).
    twice = [EntityRecord("/same", 1, 0, 1, 1, [], []), EntityRecord("/same", 2, 0, 2, 2, [], [])]
    with pytest.raises(sa.exc.IntegrityError):
        queries.save_run(session, _record(entities=twice), NOW)


def test_a_sealed_run_and_its_lifecycle_are_one_lookup(session: Session):
    record = _record(status="closed", ended_at=NOW)
    queries.save_run(session, record, NOW)
    session.flush()
    assert queries.run_and_lifecycle(session, "run-1") is None  # not sealed: no lifecycle
    queries.record_promotion(session, record, "warm/run-1", [], NOW, "sealed")
    session.flush()
    found = queries.run_and_lifecycle(session, "run-1")
    assert found is not None
    run, life = found
    assert (run.id, run.status, life.run_id, life.prefix) == ("run-1", "closed", "run-1", "warm/run-1")
    assert queries.run_and_lifecycle(session, "no-such-run") is None
    assert queries.run_and_lifecycle(session, "../x") is None
