"""Saved queries in the catalog (`catalog.saved_queries`), identical on DuckDB and Postgres."""

from __future__ import annotations

import datetime as dt

import pytest
from sqlalchemy.orm import Session

from catalog import saved_queries
from catalog.saved_queries import NameTakenError, SavedQueryRecord
from core.errors import NotFoundError

T0 = dt.datetime(2026, 11, 26, 9, 30, tzinfo=dt.UTC)


def _record(query_id: str, name: str, sql: str = "SELECT 1 AS x, 2 AS y", chart: str = "bar") -> SavedQueryRecord:
    return SavedQueryRecord(query_id, name, sql, chart, "alice", T0, T0)


def test_save_list_get_delete(session: Session) -> None:
    saved_queries.add_query(session, _record("q-000000000002", "runs per robot", "SELECT robot_id, count(*) FROM runs"))
    saved_queries.add_query(session, _record("q-000000000001", "battery per robot", chart="line"))
    listed = saved_queries.saved_queries(session)
    assert [q.name for q in listed] == ["battery per robot", "runs per robot"]  # by name
    got = saved_queries.saved_query(session, "q-000000000002")
    assert got is not None
    assert (got.sql, got.chart, got.created_by, got.created_at) == (
        "SELECT robot_id, count(*) FROM runs",
        "bar",
        "alice",
        T0,
    )
    assert got.to_dict()["created_at"] == "2026-11-26T09:30:00Z"
    gone = saved_queries.delete_query(session, "q-000000000001")
    assert gone.name == "battery per robot"
    assert [q.id for q in saved_queries.saved_queries(session)] == ["q-000000000002"]
    assert saved_queries.saved_query(session, "q-000000000001") is None


def test_names_are_unique(session: Session) -> None:
    saved_queries.add_query(session, _record("q-00000000000a", "fleet size"))
    with pytest.raises(NameTakenError, match="already named 'fleet size'") as info:
        saved_queries.add_query(session, _record("q-00000000000b", "fleet size"))
    assert info.value.http_status() == 409
    assert len(saved_queries.saved_queries(session)) == 1
    saved_queries.delete_query(session, "q-00000000000a")  # a deleted query's name is free again
    saved_queries.add_query(session, _record("q-00000000000c", "fleet size"))
    assert [q.id for q in saved_queries.saved_queries(session)] == ["q-00000000000c"]


def test_deleting_an_unknown_query_is_not_found(session: Session) -> None:
    with pytest.raises(NotFoundError, match="no saved query 'q-missing'"):
        saved_queries.delete_query(session, "q-missing")
