"""The migrations build exactly the models, on both catalog databases, from one head."""

from __future__ import annotations

import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory

from catalog.db import alembic_config, check_schema, create_engine, current_revision, head_revision
from catalog.db import upgrade as upgrade_catalog
from catalog.models import Base
from core.errors import UnavailableError


def test_one_head():
    heads = ScriptDirectory.from_config(alembic_config()).get_heads()
    assert len(heads) == 1
    assert head_revision() == heads[0]


def test_models_match_migrations(engine: sa.Engine):
    if engine.dialect.name == "duckdb":
        # The DuckDB dialect cannot reflect for Alembic: compare tables, columns and nullability.
        with engine.connect() as conn:
            rows = conn.execute(
                sa.text(
                    "select table_name, column_name, is_nullable from information_schema.columns "
                    "where table_name != 'alembic_version'"
                )
            ).all()
        built = {(t, c, n == "YES") for t, c, n in rows}
        modelled = {(t.name, c.name, bool(c.nullable)) for t in Base.metadata.sorted_tables for c in t.columns}
        assert built == modelled, f"models and migrations differ, add a migration: {built ^ modelled}"
        return
    with engine.connect() as conn:
        context = MigrationContext.configure(conn, opts={"compare_type": True})
        diff = compare_metadata(context, Base.metadata)
    assert diff == [], f"models and migrations differ, add a migration: {diff}"


def test_upgrade_from_empty_and_check(empty_catalog_url: str):
    engine = create_engine(empty_catalog_url)
    try:
        with pytest.raises(UnavailableError, match="fleet db upgrade") as info:
            check_schema(engine)
        assert "empty" in str(info.value)
        before, after = upgrade_catalog(engine)
        assert (before, after) == (None, head_revision())
        assert current_revision(engine) == head_revision()
        check_schema(engine)  # no error once at head
        assert upgrade_catalog(engine) == (head_revision(), head_revision())  # idempotent
        tables = set(sa.inspect(engine).get_table_names())
        assert {"robots", "runs", "run_entities", "run_timelines", "alembic_version"} <= tables
    finally:
        engine.dispose()


def test_unsupported_url_is_one_clear_error():
    with pytest.raises(UnavailableError, match="duckdb:///PATH or postgresql"):
        create_engine("mysql://somewhere/db")
