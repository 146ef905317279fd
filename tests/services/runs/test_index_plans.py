"""Finding runs at a million runs: the statements `GET /v1/runs` and the overview send are ones
Postgres answers from migration 0016's indexes (a sort or filter on an expression that is not the
indexed one would read every run), and the overview still finds the last run of a robot the catalog
has no row of."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.models import Robot
from services.runs import fleet, totals
from services.runs.service import RunFilter, list_runs
from tests.catalog.records import run_record
from tests.postgres import index_only_session

AT = dt.datetime(2026, 12, 5, 12, 0, tzinfo=dt.UTC)


@pytest.fixture
def planner(postgres_url: str) -> Iterator[Session]:
    """A session on a migrated Postgres catalog holding a few runs, where a statement that cannot be
    answered from an index shows it in its plan (`tests.postgres.index_only_session`)."""
    with index_only_session(postgres_url) as session:
        for n in range(3):
            queries.save_run(session, run_record(f"run-{n}", AT - dt.timedelta(hours=n), bytes=n), AT)
        session.flush()
        yield session


def _plans(session: Session, call: Callable[[], Any]) -> list[str]:
    """The plan of each statement `call` sends (EXPLAIN, with its parameters)."""
    sent: list[tuple[str, Any]] = []

    def before(conn: Any, cursor: Any, statement: str, parameters: Any, context: Any, many: bool) -> None:
        sent.append((statement, parameters))

    engine = session.get_bind().engine
    sa.event.listen(engine, "before_cursor_execute", before)
    try:
        call()
    finally:
        sa.event.remove(engine, "before_cursor_execute", before)
    raw: Any = session.connection().connection.driver_connection
    plans = []
    for statement, parameters in sent:
        with raw.cursor() as cursor:
            cursor.execute("EXPLAIN " + statement, parameters or None)
            plans.append("\n".join(row[0] for row in cursor.fetchall()))
    return plans


@pytest.mark.postgres
@pytest.mark.parametrize(
    ("asked", "index"),
    [
        ({}, "ix_runs_started"),
        ({"sort": "started_at"}, "ix_runs_started"),
        ({"robot": ["robot-7"]}, "ix_runs_robot_started"),
        ({"sort": "-bytes"}, "ix_runs_bytes"),
        ({"sort": "-metric.distance_m"}, "ix_run_metrics_name_value"),
    ],
)
def test_run_lists_read_an_index(planner: Session, asked: dict[str, Any], index: str):
    plans = _plans(planner, lambda: list_runs(planner, RunFilter(**asked)))
    assert index in plans[0], plans[0]


@pytest.mark.postgres
def test_the_next_page_starts_in_the_index_where_the_cursor_is(planner: Session):
    _, cursor = list_runs(planner, RunFilter(limit=1))
    plans = _plans(planner, lambda: list_runs(planner, RunFilter(limit=1, cursor=cursor)))
    assert "Index Cond" in plans[0] and "ix_runs_started" in plans[0], plans[0]


@pytest.mark.postgres
def test_the_overview_probes_each_robots_last_run(planner: Session):
    plans = _plans(planner, lambda: fleet.last_runs(planner, ["robot-without-a-row"]))
    assert all("ix_runs_robot_started" in plan for plan in plans), plans


def test_a_robot_without_a_row_still_has_its_last_run(catalog: sessionmaker[Session]):
    with session_scope(catalog, write=True) as session:
        for n, robot in enumerate(["robot-a", "robot-a", "robot-b", "robot-b"]):
            started = AT - dt.timedelta(hours=n)
            queries.save_run(session, run_record(f"run-{n}", started, robot_id=robot, tier="warm"), started)
        session.flush()
        session.execute(sa.delete(Robot).where(Robot.id == "robot-b"))  # a catalog rebuilt from runs alone
    with session_scope(catalog) as session:
        found = fleet.robots(session, totals.count(session).robots)
        listed = {r["id"]: (r["runs"], r["last_run"]["id"], r["last_seen_at"]) for r in found}
    assert listed == {"robot-a": (2, "run-0", listed["robot-a"][2]), "robot-b": (2, "run-2", None)}
