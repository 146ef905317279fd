"""The overview's whole-fleet sums (services/runs/totals.py), on DuckDB and Postgres: a small fleet
is counted as the overview asks; a big one shows the job's last count, and when it was made, until
that count is too old."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from services.runs import totals
from tests.catalog.records import run_record

NOW = dt.datetime(2026, 11, 30, 12, 0, tzinfo=dt.UTC)


def add(catalog: sessionmaker[Session], *run_ids: str, robot: str = "robot-a") -> None:
    with session_scope(catalog, write=True) as session:
        for run_id in run_ids:
            queries.save_run(session, run_record(run_id, NOW, robot_id=robot, tier="warm", bytes=100), NOW)


def shown(catalog: sessionmaker[Session], now: dt.datetime) -> totals.Totals:
    with session_scope(catalog) as session:
        return totals.totals(session, now)


@pytest.fixture
def big_at_two(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setattr(totals, "BIG_FLEET", 2)  # a fleet of two runs is big here
    yield


def test_a_small_fleet_is_counted_as_the_overview_asks(catalog: sessionmaker[Session]):
    add(catalog, "run-1")
    assert totals.count_job(catalog, NOW) == 1
    add(catalog, "run-2")
    now = shown(catalog, NOW + dt.timedelta(seconds=1))
    assert now.counted_at is None and now.robots == {"robot-a": 2}


def test_a_big_fleet_shows_the_jobs_last_count_until_it_is_too_old(catalog: sessionmaker[Session], big_at_two: None):
    add(catalog, "run-1", "run-2")
    assert totals.count_job(catalog, NOW) == 2
    add(catalog, "run-3", robot="robot-b")
    later = NOW + dt.timedelta(seconds=30)
    kept = shown(catalog, later)
    assert kept.counted_at == "2026-11-30T12:00:00Z" and kept.robots == {"robot-a": 2}
    assert [t["runs"] for t in kept.tiers] == [0, 2, 0, 0] and kept.objects[0]["tier"] == "warm"
    assert totals.count_job(catalog, later) is None  # counted less than an interval ago (by any node)
    assert totals.count_job(catalog, NOW + dt.timedelta(seconds=totals.COUNT_INTERVAL_S)) == 3
    assert shown(catalog, NOW + dt.timedelta(seconds=totals.COUNT_INTERVAL_S + 1)).robots == {
        "robot-a": 2,
        "robot-b": 1,
    }
    stale = shown(catalog, NOW + totals.STALE_AFTER + dt.timedelta(seconds=totals.COUNT_INTERVAL_S + 1))
    assert stale.counted_at is None and stale.runs == 3  # the job stopped: counted for the answer
