"""The migrations build exactly the models, on both catalog databases, from one head."""

from __future__ import annotations

import datetime as dt
import re

import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory

from catalog.db import alembic_config, check_schema, create_engine, current_revision, head_revision
from catalog.db import upgrade as upgrade_catalog
from catalog.models import Base, Run
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


def _upgrade_to(engine: sa.Engine, revision: str) -> None:
    from alembic import command

    with engine.begin() as conn:
        config = alembic_config()
        config.attributes["connection"] = conn
        command.upgrade(config, revision)


def _run_row(run_id: str, application_id: str) -> dict[str, object]:
    now = dt.datetime(2026, 11, 20, 8, 0, tzinfo=dt.UTC)
    return {
        "id": run_id,
        "robot_id": "robot-1",
        "application_id": application_id,
        "date": now.date(),
        "status": "closed",
        "tier": "warm",
        "started_at": now,
        "ended_at": now,
        "last_data_at": now,
        "sdk_version": "0.41.0",
        "chunks": 1,
        "rows": 1,
        "bytes": 1,
        "properties": "{}",
        "pinned": False,
        "pinned_by": None,
        "created_at": now,
        "updated_at": now,
    }


def test_0006_gives_every_application_already_catalogued_a_dataset(empty_catalog_url: str):
    engine = create_engine(empty_catalog_url)
    try:
        _upgrade_to(engine, "0005")
        runs = [("run-1", "nav"), ("run-2", "nav"), ("run-3", "arm"), ("run-4", "")]
        with engine.begin() as conn:
            conn.execute(sa.insert(Run), [_run_row(run, app) for run, app in runs])
        before = dt.datetime.now(dt.UTC)
        upgrade_catalog(engine)
        with engine.connect() as conn:
            found = {name: entry for name, entry in conn.execute(sa.text("SELECT name, entry_id FROM datasets"))}
    finally:
        engine.dispose()
    assert sorted(found) == ["arm", "nav"]  # one per application id; a run without one makes none
    assert len(set(found.values())) == 2
    for entry_id in found.values():
        assert re.fullmatch(r"[0-9A-F]{16}[0-9a-f]{16}", entry_id), entry_id
        made = dt.datetime.fromtimestamp(int(entry_id[:16], 16) / 1e9, dt.UTC)  # a TUID: its time first
        assert before - dt.timedelta(seconds=1) <= made <= dt.datetime.now(dt.UTC)


def test_0012_makes_every_pull_already_queued_a_persons(empty_catalog_url: str):
    engine = create_engine(empty_catalog_url)
    now = dt.datetime(2026, 11, 29, 8, 0, tzinfo=dt.UTC)
    try:
        _upgrade_to(engine, "0011")
        with engine.begin() as conn:
            conn.execute(
                sa.text(
                    "INSERT INTO pulls (id, run_id, robot_id, include, exclude, state, requested_by, requested_at, "
                    "updated_at, chunks_sent, bytes_sent) VALUES ('pull-000000000001', 'run-1', 'robot-1', '[]', "
                    "'[]', 'pending', 'alice', :now, :now, 0, 0)"
                ),
                {"now": now},
            )
        upgrade_catalog(engine)
        with engine.connect() as conn:
            found = conn.execute(sa.text("SELECT origin, event_id, priority FROM pulls")).all()
        with engine.begin() as conn:  # a pull written without an origin is a person's
            conn.execute(
                sa.text(
                    "INSERT INTO pulls (id, run_id, robot_id, include, exclude, state, requested_by, requested_at, "
                    "updated_at, chunks_sent, bytes_sent) VALUES ('pull-000000000002', 'run-1', 'robot-1', '[]', "
                    "'[]', 'held', 'x', :now, :now, 0, 0)"
                ),
                {"now": now},
            )
            added = conn.execute(sa.text("SELECT origin FROM pulls WHERE id = 'pull-000000000002'")).scalar()
            with pytest.raises(sa.exc.DBAPIError), conn.begin_nested():  # never without one
                conn.execute(sa.text("UPDATE pulls SET origin = NULL"))
    finally:
        engine.dispose()
    assert [tuple(row) for row in found] == [("person", None, None)]
    assert added == "person"


def test_0013_adds_the_snapshot_tables_and_takes_them_away_again(empty_catalog_url: str):
    from alembic import command

    engine = create_engine(empty_catalog_url)
    tables = ("dataset_snapshots", "dataset_versions", "dataset_episodes")
    try:
        _upgrade_to(engine, "0012")
        assert not set(tables) & set(sa.inspect(engine).get_table_names())
        _upgrade_to(engine, "0013")
        assert set(tables) <= set(sa.inspect(engine).get_table_names())
        with engine.begin() as conn:  # an episode holds its chunk ids as bytes, and a whole run no range
            conn.execute(
                sa.text(
                    "INSERT INTO dataset_episodes (name, version, episode, run_id, robot_id, split, timeline, "
                    "range_start, range_end, event_id, chunk_ids, chunks, bytes) VALUES ('a', 1, 0, 'run-1', "
                    "'robot-1', NULL, 'log_time', NULL, NULL, NULL, :ids, 2, 20)"
                ),
                {"ids": b"\x00" * 16 + b"\xff" * 16},
            )
            held = conn.execute(sa.text("SELECT chunk_ids FROM dataset_episodes")).scalar()
        duckdb = engine.dialect.name == "duckdb"  # primary keys only there (and no reflection of indexes)
        indexes = set() if duckdb else {i["name"] for i in sa.inspect(engine).get_indexes("dataset_episodes")}
        with engine.begin() as conn:
            config = alembic_config()
            config.attributes["connection"] = conn
            command.downgrade(config, "0012")
        assert not set(tables) & set(sa.inspect(engine).get_table_names())
    finally:
        engine.dispose()
    assert held is not None and bytes(held) == b"\x00" * 16 + b"\xff" * 16
    assert indexes == (set() if duckdb else {"ix_dataset_episodes_run_id"})
