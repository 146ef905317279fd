"""Catalog fixtures: every catalog test runs against embedded DuckDB and a real Postgres.

Postgres: a fresh database per test session on the local server (127.0.0.1:5432, trust auth),
upgraded to the head revision, dropped at the end; each test runs in a transaction that is rolled
back, so tests do not see each other's rows.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.db import create_engine, upgrade
from tests.postgres import temporary_database


@pytest.fixture(scope="session")
def postgres_url() -> Iterator[str]:
    with temporary_database("fleet_test") as url:
        yield url


@pytest.fixture(scope="session")
def duckdb_url(tmp_path_factory: pytest.TempPathFactory) -> str:
    return f"duckdb:///{tmp_path_factory.mktemp('catalog') / 'catalog.duckdb'}"


@pytest.fixture(scope="session", params=["duckdb", pytest.param("postgres", marks=pytest.mark.postgres)])
def catalog_url(request: pytest.FixtureRequest) -> str:
    url: str = request.getfixturevalue(f"{request.param}_url")
    return url


@pytest.fixture(scope="session")
def engine(catalog_url: str) -> Iterator[sa.Engine]:
    engine = create_engine(catalog_url)
    upgrade(engine)
    yield engine
    engine.dispose()


@pytest.fixture
def session(engine: sa.Engine) -> Iterator[Session]:
    """A session inside a transaction that is rolled back after the test."""
    with engine.connect() as conn:
        outer = conn.begin()
        session = Session(bind=conn, join_transaction_mode="rollback_only")  # DuckDB has no savepoints
        try:
            yield session
        finally:
            session.close()
            outer.rollback()


@pytest.fixture
def empty_catalog_url(catalog_url: str, tmp_path: Path) -> Iterator[str]:
    """A catalog with no schema at all, of the same kind."""
    if catalog_url.startswith("duckdb"):
        yield f"duckdb:///{tmp_path / 'empty.duckdb'}"
        return
    with temporary_database("fleet_empty") as url:
        yield url
