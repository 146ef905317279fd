"""Migration 0016's indexes (a catalog of a million runs): made on Postgres and taken away again,
none on the embedded catalog; and the catalog's own queries written so Postgres can use them (the
expression a query sorts or filters by must be the indexed one, or the index is never read)."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from typing import Any

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog import queries
from catalog.db import alembic_config, create_engine
from catalog.db import upgrade as upgrade_catalog
from catalog.models import Run
from core.states import Tier
from tests.postgres import index_only_session

NEW = {
    "runs": {
        "ix_runs_started",
        "ix_runs_robot_started",
        "ix_runs_bytes",
        "ix_runs_tier_end",
        "ix_runs_application_tier_end",
    },
    "run_metrics": {"ix_run_metrics_name_value"},
    "retention_events": {"ix_retention_events_occurred_at"},
    "job_runs": {"ix_job_runs_started_at"},
    "run_lifecycle": {"ix_run_lifecycle_restore_state"},
}


def _indexes(engine: sa.Engine) -> dict[str, set[str]]:
    if engine.dialect.name == "duckdb":  # no reflection of indexes there: ask DuckDB itself
        with engine.connect() as conn:
            rows = conn.execute(sa.text("SELECT table_name, index_name FROM duckdb_indexes()")).all()
        found: dict[str, set[str]] = {table: set() for table in NEW}
        for table, name in rows:
            found.setdefault(table, set()).add(name)
        return found
    inspector = sa.inspect(engine)
    return {table: {str(i["name"]) for i in inspector.get_indexes(table)} for table in NEW}


def _migrate(engine: sa.Engine, revision: str, *, down: bool = False) -> None:
    from alembic import command

    with engine.begin() as conn:
        config = alembic_config()
        config.attributes["connection"] = conn
        (command.downgrade if down else command.upgrade)(config, revision)


def test_0016_indexes_postgres_and_leaves_the_embedded_catalog_with_primary_keys(empty_catalog_url: str):
    engine = create_engine(empty_catalog_url)
    try:
        upgrade_catalog(engine)
        at_head = _indexes(engine)
        _migrate(engine, "0015", down=True)
        before = _indexes(engine)
    finally:
        engine.dispose()
    if engine.dialect.name == "duckdb":
        assert at_head == before and not any(at_head.values())
        return
    for table, names in NEW.items():
        assert names <= at_head[table] and not names & before[table], table
    for table, replaced in (("run_metrics", "ix_run_metrics_name"), ("runs", "ix_runs_application_id")):
        assert replaced in before[table] and replaced not in at_head[table]


@pytest.fixture
def pg_session(postgres_url: str) -> Iterator[Session]:
    """A session on a migrated Postgres catalog where a query that cannot read an index shows it."""
    with index_only_session(postgres_url) as session:
        yield session


def _plan(session: Session, query: sa.Select[Any]) -> str:
    compiled = query.compile(session.get_bind(), compile_kwargs={"literal_binds": True})
    return "\n".join(row[0] for row in session.execute(sa.text(f"EXPLAIN {compiled}")))


@pytest.mark.postgres
def test_runs_newest_first_read_the_start_index(pg_session: Session):
    started = sa.func.coalesce(Run.started_at, Run.created_at)
    query = sa.select(Run.id).where(Run.tier != Tier.DELETED).order_by(started.desc(), Run.id.desc()).limit(10)
    assert "ix_runs_started" in _plan(pg_session, query)


@pytest.mark.postgres
def test_retentions_candidates_are_read_by_tier_and_end(pg_session: Session):
    cutoff = dt.datetime(2026, 1, 1, tzinfo=dt.UTC)
    due = sa.select(Run.id).where(Run.tier.in_((Tier.WARM, Tier.COLD)), queries.run_end() <= cutoff)
    assert "ix_runs_tier_end" in _plan(pg_session, due)
    assert queries.sealed_runs(pg_session, (Tier.WARM, Tier.COLD), queries.run_end() <= cutoff) == []
