"""The corpus over POST /v1/sql: `run_metrics`, `events` and `run_tags` hold the rows the catalog
holds (on DuckDB and Postgres), with the documented columns and types, and a search written in SQL
keeps the runs `GET /v1/runs` keeps."""

from __future__ import annotations

import datetime as dt
import io
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pyarrow as pa
import pytest
import sqlalchemy as sa
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import create_engine, session_scope
from catalog.models import Event, RunMetric, RunTag
from services.analytics.saved import tables
from services.analytics.service import Analytics
from services.analytics.sql import Limits
from services.api.app import create_app
from services.runs import service
from services.runs.service import RunFilter
from services.sealed.tiers import Tiers
from services.storage.objectstore import open_store
from tests.services.analytics.conftest import opened, sql_rows
from tests.services.nodes import node_of
from tests.services.runs.corpus_scene import expected, write_scene

COLUMNS = {
    "run_metrics": [
        ("run_id", pa.string()),
        ("robot_id", pa.string()),
        ("name", pa.string()),
        ("value", pa.float64()),
        ("text_value", pa.string()),
        ("rules_version", pa.int64()),
    ],
    "events": [
        ("id", pa.string()),
        ("run_id", pa.string()),
        ("robot_id", pa.string()),
        ("kind", pa.string()),
        ("severity", pa.string()),
        ("timeline", pa.string()),
        ("timeline_type", pa.string()),
        ("start", pa.int64()),
        ("end", pa.int64()),
        ("source", pa.string()),
        ("origin", pa.string()),
        ("rules_version", pa.int64()),
        ("label", pa.string()),
        ("note", pa.string()),
        ("created_at", pa.timestamp("us", tz="UTC")),
    ],
    "run_tags": [("run_id", pa.string()), ("tag", pa.string()), ("added_by", pa.string())],
}


@pytest.fixture
def scene(fresh_catalog_url: str) -> Iterator[sessionmaker[Session]]:
    engine = create_engine(fresh_catalog_url)
    catalog = sessionmaker(engine)
    with session_scope(catalog, write=True) as session:
        write_scene(session)
    yield catalog
    engine.dispose()


@pytest.fixture
def client(scene: sessionmaker[Session], tmp_path: Path) -> TestClient:
    store = open_store((tmp_path / "warm").as_uri())
    node = node_of(tmp_path, scene, tiers=Tiers(store, store))
    return TestClient(create_app(node, analytics=opened(Analytics(node, Limits()))))


def arrow(client: TestClient, query: str) -> pa.Table:
    answer = client.post("/v1/sql", json={"query": query}, headers={"Accept": "application/vnd.apache.arrow.stream"})
    assert answer.status_code == 200, answer.text
    return pa.ipc.open_stream(io.BytesIO(answer.content)).read_all()


def catalog_rows(catalog: sessionmaker[Session], table: str) -> list[dict[str, Any]]:
    """The catalog's own rows of a corpus table, named as SQL names them."""
    with session_scope(catalog) as session:
        if table == "run_metrics":
            return [
                {
                    "run_id": m.run_id,
                    "robot_id": m.robot_id,
                    "name": m.name,
                    "value": m.value,
                    "text_value": m.text_value,
                    "rules_version": m.rules_version,
                }
                for m in session.scalars(sa.select(RunMetric))
            ]
        if table == "run_tags":
            return [
                {"run_id": t.run_id, "tag": t.tag, "added_by": t.added_by} for t in session.scalars(sa.select(RunTag))
            ]
        return [
            {
                "id": e.id,
                "run_id": e.run_id,
                "robot_id": e.robot_id,
                "kind": e.kind,
                "severity": e.severity,
                "timeline": e.timeline,
                "timeline_type": e.timeline_type,
                "start": e.range_start,
                "end": e.range_end,
                "source": e.source,
                "origin": e.origin,
                "rules_version": e.rules_version,
                "label": e.label,
                "note": e.note,
                "created_at": e.created_at.astimezone(dt.UTC),
            }
            for e in session.scalars(sa.select(Event))
        ]


def plain_zone(kind: pa.DataType) -> pa.DataType:
    """DuckDB names UTC Etc/UTC: the same zone."""
    if pa.types.is_timestamp(kind) and kind.tz == "Etc/UTC":
        return pa.timestamp(kind.unit, tz="UTC")
    return kind


def ordered(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return sorted(rows, key=lambda r: tuple(str(v) for v in r.values()))


@pytest.mark.parametrize("table", sorted(COLUMNS))
def test_corpus_tables_hold_the_catalogs_rows(client: TestClient, scene: sessionmaker[Session], table: str):
    answer = arrow(client, f"SELECT * FROM {table}")
    assert [(f.name, plain_zone(f.type)) for f in answer.schema] == COLUMNS[table]
    held = catalog_rows(scene, table)
    assert len(held) >= 5  # the scene fills each table
    assert ordered(answer.to_pylist()) == ordered(held)


def test_a_search_in_sql_keeps_the_runs_rest_keeps(client: TestClient, scene: sessionmaker[Session]):
    query = """
        SELECT DISTINCT m.run_id FROM run_metrics m
        JOIN run_tags t ON t.run_id = m.run_id AND t.tag = 'dock-2'
        WHERE m.name = 'distance_m' AND m.value >= 100
          AND EXISTS (SELECT 1 FROM events e WHERE e.run_id = m.run_id AND e.kind = 'intervention')
        ORDER BY 1"""
    flt = {"metric": ["distance_m>=100"], "tag": ["dock-2"], "event": ["intervention"]}
    with session_scope(scene) as session:
        runs, _ = service.list_runs(session, RunFilter(sort="id", **flt))  # type: ignore[arg-type]
        found = [r.id for r in runs]
    assert [r["run_id"] for r in sql_rows(client, query)] == found == expected(flt) == ["r-1"]
    texts = sql_rows(client, "SELECT run_id FROM run_metrics WHERE text_value = '2.3' ORDER BY 1")
    assert [r["run_id"] for r in texts] == expected({"metric": ["sw_version=2.3"]})
    spans = sql_rows(client, "SELECT sum(\"end\" - start) AS ns FROM events WHERE kind = 'intervention'")
    assert spans == [{"ns": 4 * 2 * 10**9}]  # r-1 twice, r-3, r-5 (a person's), 2 s each


def test_the_sql_page_lists_the_corpus_tables_and_their_columns():
    guides = {g.name: g for g in tables()}
    for name, columns in COLUMNS.items():
        assert guides[name].kind == "catalog"
        assert [c for c, _ in guides[name].columns] == [c for c, _ in columns]
    assert dict(guides["run_metrics"].columns)["value"] == "DOUBLE"
