"""The fleet overview's figures, on DuckDB and Postgres alike: robots and their last runs, runs per
robot per day, data by tier, object-store usage, retention jobs and events, live runs, disk usage."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import create_engine, session_scope
from catalog.models import Robot
from catalog.queries import ObjectRecord
from services.runs import fleet, totals
from tests.catalog.records import run_record
from tests.services.nodes import node_of

NOW = dt.datetime(2026, 11, 20, 12, 0, tzinfo=dt.UTC)


def _add(
    session: Session,
    run_id: str,
    robot: str,
    days_ago: float,
    *,
    tier: str = "warm",
    status: str = "closed",
    size: int = 100,
    started: bool = True,
) -> None:
    start = NOW - dt.timedelta(days=days_ago)
    queries.save_run(
        session,
        run_record(
            run_id,
            start,
            robot_id=robot,
            status=status,
            tier=tier,
            started_at=start if started else None,
            ended_at=None if status == "live" else start + dt.timedelta(minutes=5),
            last_data_at=start + dt.timedelta(minutes=5),
            chunks=3,
            rows=30,
            bytes=size,
        ),
        start,
    )


def _objects(session: Session, run_id: str, tier: str, *sizes: int) -> None:
    queries.replace_objects(
        session, run_id, [ObjectRecord(f"o{i}", f"{run_id}/o{i}", tier, size, "0" * 64) for i, size in enumerate(sizes)]
    )


@pytest.fixture
def fleet_rows(session: Session) -> Session:
    _add(session, "a-old", "robot-a", 20, size=1000)  # outside the 14 days
    _add(session, "a-1", "robot-a", 2, size=300)
    _add(session, "a-2", "robot-a", 0.1, tier="hot", status="live", size=50)
    _add(session, "a-gone", "robot-a", 0, tier="deleted", size=7000)  # a tombstone: newest, yet not the last run
    _add(session, "b-1", "robot-b", 1, tier="cold", size=200)
    _add(session, "b-2", "robot-b", 1, tier="hot", size=20)
    session.add(Robot(id="robot-idle", created_at=NOW, last_seen_at=NOW))
    _objects(session, "a-old", "warm", 1000, 10)
    _objects(session, "a-1", "warm", 300, 5)
    _objects(session, "b-1", "cold", 200, 4)
    session.flush()
    return session


def test_robots_with_last_runs_and_counts(fleet_rows: Session):
    robots = {r["id"]: r for r in fleet.robots(fleet_rows, totals.count(fleet_rows).robots)}
    assert list(robots) == ["robot-a", "robot-b", "robot-idle"]
    assert robots["robot-a"]["runs"] == 3  # the deleted run is not counted
    assert robots["robot-a"]["last_run"]["id"] == "a-2" and robots["robot-a"]["last_run"]["status"] == "live"
    # b-1 and b-2 started at the same time: the larger id wins, as in GET /v1/runs's newest-first order
    assert robots["robot-b"]["runs"] == 2 and robots["robot-b"]["last_run"]["id"] == "b-2"
    assert robots["robot-idle"] == {
        "id": "robot-idle",
        "runs": 0,
        "last_seen_at": "2026-11-20T12:00:00Z",
        "last_run": None,
    }


def test_runs_per_day(fleet_rows: Session):
    per_day = fleet.runs_per_day(fleet_rows, NOW.date())
    assert len(per_day["days"]) == fleet.DAYS and per_day["days"][-1] == "2026-11-20"
    assert per_day["days"][0] == "2026-11-07"
    counts = {r["id"]: r["counts"] for r in per_day["robots"]}
    assert counts["robot-a"][-3] == 1 and counts["robot-a"][-1] == 1  # a-1 two days ago, a-2 today
    assert sum(counts["robot-a"]) == 2  # neither the 20-day-old run nor the tombstone
    assert counts["robot-b"][-2] == 2 and sum(counts["robot-b"]) == 2
    assert per_day["totals"][-2] == 2 and per_day["max"] == 2
    assert "robot-idle" not in counts


def test_tier_and_object_totals(fleet_rows: Session):
    counted = totals.count(fleet_rows)
    tiers = {t["tier"]: t for t in counted.tiers}
    assert [t["tier"] for t in counted.tiers] == ["hot", "warm", "cold", "deleted"]
    assert tiers["hot"] == {"tier": "hot", "runs": 2, "bytes": 70}
    assert tiers["warm"] == {"tier": "warm", "runs": 2, "bytes": 1300}
    assert tiers["cold"] == {"tier": "cold", "runs": 1, "bytes": 200}
    assert tiers["deleted"] == {"tier": "deleted", "runs": 1, "bytes": None}
    assert counted.runs == 6 and counted.robots == {"robot-a": 3, "robot-b": 2}
    assert counted.objects == [
        {"tier": "warm", "objects": 4, "bytes": 1315},
        {"tier": "cold", "objects": 2, "bytes": 204},
    ]


def test_jobs_failures_and_events(fleet_rows: Session):
    for i, outcome in enumerate(("ok", "failed", "ok", "running")):
        job_id = queries.start_job(
            fleet_rows, "retention" if i % 2 else "promote", "node-1", NOW + dt.timedelta(minutes=i)
        )
        if outcome != "running":
            queries.finish_job(fleet_rows, job_id, NOW + dt.timedelta(minutes=i, seconds=30), outcome, f"{outcome} {i}")
    for i, action in enumerate(("promote", "archive", "delete")):
        queries.add_event(fleet_rows, "a-1", action, NOW + dt.timedelta(hours=i), "retention", "default", action)
    fleet_rows.flush()
    jobs = fleet.recent_jobs(fleet_rows)
    assert [j["outcome"] for j in jobs] == ["running", "ok", "failed", "ok"]  # newest first
    assert [j["failed"] for j in jobs] == [False, False, True, False]
    assert jobs[0]["finished_at"] is None and jobs[0]["seconds"] is None and jobs[1]["seconds"] == 30
    failures = fleet.failed_jobs(fleet_rows)
    assert [(f["job"], f["detail"]) for f in failures] == [("retention", "failed 1")]
    assert len(fleet.recent_jobs(fleet_rows, limit=2)) == 2
    events = fleet.recent_events(fleet_rows)
    assert [e["action"] for e in events] == ["delete", "archive", "promote"]
    assert events[0] == {
        "run_id": "a-1",
        "action": "delete",
        "at": "2026-11-20T14:00:00Z",
        "actor": "retention",
        "policy": "default",
        "detail": "delete",
    }


def test_live_runs_merge_this_nodes_hot_runs(fleet_rows: Session):
    live = fleet.live_in_catalog(fleet_rows)
    assert [r["id"] for r in live] == ["a-2"] and live[0]["here"] is False
    fresher = {**live[0], "bytes": 5000, "here": True}
    waiting = {**live[0], "id": "b-9", "status": "closed", "last_data_at": "2026-11-19T00:00:00Z", "here": True}
    merged = fleet.live_now(live, [fresher, waiting])
    assert [(r["id"], r["bytes"], r["here"]) for r in merged] == [("a-2", 5000, True), ("b-9", 50, True)]


def test_disk_usage(tmp_path: Path):
    usage = fleet.disk_usage(tmp_path, reserve=123)
    assert usage["path"] == str(tmp_path) and usage["reserve"] == 123
    assert usage["used"] + usage["free"] <= usage["total"] and 0 < usage["used_fraction"] < 1
    assert fleet.hot_disk(None, []) is None and fleet.hot_here(None, "robot-0") == []


def test_overview_answer(fresh_catalog_url: str, tmp_path: Path):
    engine = create_engine(fresh_catalog_url)
    try:
        catalog = sessionmaker(engine)
        with session_scope(catalog, write=True) as session:
            _add(session, "a-1", "robot-a", 1, size=300)
            _add(session, "a-2", "robot-a", 0, tier="hot", status="live", size=40, started=False)
        answer = fleet.overview(node_of(tmp_path, catalog), None, now=NOW)
    finally:
        engine.dispose()
    assert answer["generated_at"] == "2026-11-20T12:00:00Z"
    assert [r["last_run"]["id"] for r in answer["robots"]] == ["a-2"]  # no start: its creation time counts
    assert [t["runs"] for t in answer["tiers"]] == [1, 1, 0, 0]
    assert [r["id"] for r in answer["live"]] == ["a-2"] and answer["hot_disk"] is None
    assert answer["per_day"]["totals"][-2:] == [1, 1]
    assert answer["jobs"] == [] and answer["failures"] == [] and answer["events"] == []
    assert answer["totals_counted_at"] is None  # a small fleet: counted for the answer
