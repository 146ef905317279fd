"""Imports and the MCAP files held by digest in the catalog (`catalog.imports`), identical on DuckDB
and Postgres: one claim per file, the loser told who holds it, a released claim taken again; rows
listed newest first with filters and pages."""

from __future__ import annotations

import datetime as dt

from sqlalchemy.orm import Session, sessionmaker

from catalog import imports as rows
from catalog.db import session_scope
from catalog.models import Import

T0 = dt.datetime(2026, 11, 29, 8, tzinfo=dt.UTC)
DIGEST = "ab" * 32


def row(import_id: str, minute: int, state: str = rows.FILED, kind: str = "mcap") -> Import:
    at = T0 + dt.timedelta(minutes=minute)
    return Import(
        id=import_id, kind=kind, state=state, name=f"{import_id}.mcap", bytes=10, robot_id="r1", run_ids="[]",
        chunks_new=0, chunks_duplicate=0, created_by="alice", created_at=at, updated_at=at,
    )  # fmt: skip


def test_one_claim_per_file_and_a_released_claim_is_free_again(catalog: sessionmaker[Session]) -> None:
    assert rows.claim(catalog, DIGEST, "imp-a", "run-1") is None
    assert rows.claim(catalog, DIGEST, "imp-b", "run-1") == "imp-a"  # the second is told who holds it
    with session_scope(catalog, write=True) as session:
        rows.release(session, DIGEST, "imp-b")  # not its claim: nothing happens
    with session_scope(catalog) as session:
        held = rows.holder(session, DIGEST)
        assert held is not None and held.import_id == "imp-a"
    with session_scope(catalog, write=True) as session:
        rows.release(session, DIGEST, "imp-a")
    assert rows.claim(catalog, DIGEST, "imp-b", "run-1") is None


def test_imports_are_listed_newest_first_filtered_and_paged(catalog: sessionmaker[Session]) -> None:
    with session_scope(catalog, write=True) as session:
        for k in range(5):
            rows.add(session, row(f"imp-{k}", k, rows.FAILED if k % 2 else rows.FILED, "rrd" if k == 4 else "mcap"))
    with session_scope(catalog) as session:
        assert [r.id for r in rows.listed(session, state=None, kind=None, robot=None, limit=10)] == [
            "imp-4", "imp-3", "imp-2", "imp-1", "imp-0",
        ]  # fmt: skip
        failed = rows.listed(session, state=rows.FAILED, kind=None, robot=None, limit=10)
        assert [r.id for r in failed] == ["imp-3", "imp-1"]
        assert [r.id for r in rows.listed(session, state=None, kind="rrd", robot=None, limit=10)] == ["imp-4"]
        page = rows.listed(session, state=None, kind=None, robot=None, limit=2, before="imp-3")
        assert [r.id for r in page] == ["imp-2", "imp-1"]
        assert rows.listed(session, state=None, kind=None, robot="r2", limit=10) == []
