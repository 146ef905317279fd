"""Catalog writes and reads, identical on DuckDB and Postgres."""

from __future__ import annotations

import datetime as dt
import json

from sqlalchemy.orm import Session

from catalog import queries
from catalog.queries import EntityRecord, RunRecord, TimelineRecord
from core.clock import aware

NOW = dt.datetime(2026, 11, 21, 12, 0, tzinfo=dt.UTC)


def _record(**changes: object) -> RunRecord:
    record = RunRecord(
        id="run-1",
        robot_id="robot-7",
        application_id="nav",
        date=dt.date(2026, 11, 21),
        status="live",
        tier="hot",
        started_at=NOW - dt.timedelta(minutes=5),
        ended_at=None,
        last_data_at=NOW,
        sdk_version="0.41.0",
        chunks=10,
        rows=100,
        bytes=12345,
        properties={"fleet": {"robot_id": "robot-7"}},
        entities=[
            EntityRecord("/world/points", 6, 0, 60, 10000, ["rerun.archetypes.Points3D"], ["Points3D:positions"]),
            EntityRecord("/__properties/fleet", 1, 1, 1, 345, [], ["robot_id"]),
        ],
        timelines=[
            TimelineRecord("frame", "sequence", 0, 59),
            TimelineRecord("log_time", "timestamp", 1_700_000_000 * 10**9, 1_700_000_060 * 10**9),
        ],
    )
    for key, value in changes.items():
        setattr(record, key, value)
    return record


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
