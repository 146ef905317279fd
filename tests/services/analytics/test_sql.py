"""POST /v1/sql: the catalog views on both catalog databases, the analytics tables over local
files and over a real S3 server (SeaweedFS), the four answer formats, the row and time limits,
the sandbox (every refused statement and file), partition pruning; then `fleet sql` and the
Python client against a real `fleet serve`."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import json
import re
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import boto3
import httpx
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest
import sqlalchemy as sa
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import create_engine, session_scope, upgrade
from catalog.models import Run
from sdk_client.rest import FleetClient, ServiceError
from services.analytics.service import Analytics
from services.analytics.sql import Limits
from services.api.app import create_app
from services.sealed.tiers import Tiers
from services.storage.objectstore import ObjectStore, open_store
from tests.catalog.records import run_record
from tests.conftest import CATALOG_KINDS, fresh_catalog
from tests.seaweedfs import seaweedfs
from tests.services.analytics.conftest import (
    START_2026_03_01_NS,
    catalog_run,
    log_with_sdk,
    opened,
    sql_rows,
    write_scalars,
)
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.nodes import node_of

ROBOTS, DATES = ("robot-1", "robot-2", "robot-3"), ("2026-03-01", "2026-03-02")
BUCKET = "fleet-warm"
ALLOWED_ONLY = "queries read only the catalog views"  # the rule for files and URLs
READ_ONLY = "queries are read-only, only SELECT (or EXPLAIN)"  # the rule for statements


def sql_app(
    root: Path, store: ObjectStore, catalog: sessionmaker[Session], limits: Limits | None = None, **client: Any
) -> TestClient:
    """The REST app of a node (under `root`) that serves only SQL over `store` and `catalog`."""
    node = node_of(root, catalog, tiers=Tiers(store, store))
    analytics = opened(Analytics(node, limits or Limits()))
    return TestClient(create_app(node, analytics=analytics), **client)


def post(client: TestClient, query: str, **kwargs: Any) -> httpx.Response:
    response: httpx.Response = client.post("/v1/sql", json={"query": query}, **kwargs)
    return response


def files_read(client: TestClient, query: str) -> int:
    """`Total Files Read` of the query's EXPLAIN ANALYZE."""
    plan = "\n".join(str(r["explain_value"]) for r in sql_rows(client, f"EXPLAIN ANALYZE {query}"))
    found = re.findall(r"Total Files Read:\s*(\d+)", plan)
    assert len(found) == 1, plan
    return int(found[0])


def fill(store: ObjectStore, catalog: sessionmaker[Session]) -> None:
    """Two runs per robot and day, run `R-D-k` holding values k+1 .. k+3 at frames 0..2."""
    for robot in ROBOTS:
        for date in DATES:
            for k in range(2):
                run = f"{robot}-{date}-{k}"
                key = write_scalars(store, robot, date, run, [k + 1.0, k + 2.0, k + 3.0])
                catalog_run(catalog, run, robot, date, {"analytics/scalars": key})


@pytest.fixture
def blank(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[sessionmaker[Session]]:
    """An empty catalog: DuckDB, or the kind a test names (`ON_BOTH_CATALOGS`). Most tests here are
    about the SQL sandbox, the same whatever the catalog; those that are about what the catalog
    lists run on both."""
    with fresh_catalog(getattr(request, "param", "duckdb"), request, tmp_path) as url:
        engine = create_engine(url)
        yield sessionmaker(engine)
        engine.dispose()


ON_BOTH_CATALOGS = pytest.mark.parametrize("blank", CATALOG_KINDS, indirect=True)


@pytest.fixture
def local(tmp_path: Path, blank: sessionmaker[Session]) -> ObjectStore:
    store = open_store((tmp_path / "warm").as_uri())
    fill(store, blank)
    return store


# --- the catalog views, on DuckDB and on Postgres ------------------------------------------------


@pytest.fixture
def catalog(empty_catalog_url: str) -> Iterator[sessionmaker[Session]]:
    engine = create_engine(empty_catalog_url)
    upgrade(engine)
    yield sessionmaker(engine)
    engine.dispose()


@pytest.mark.slow
def test_catalog_views(catalog: sessionmaker[Session], tmp_path: Path):
    t0 = dt.datetime(2026, 3, 1, 10, 0, tzinfo=dt.UTC)
    for n, robot in enumerate(("robot-1", "robot-2")):
        record = run_record(
            f"run-{n}",
            t0,
            robot_id=robot,
            application_id="picker",
            tier="warm",
            ended_at=t0 + dt.timedelta(minutes=5),
            last_data_at=t0 + dt.timedelta(minutes=5),
            chunks=10 + n,
            rows=100,
            bytes=5_000_000_000 + n,
            properties={"fleet": {"robot_id": robot, "site": f"site-{n}"}},
            entities=[queries.EntityRecord("/battery", 2, 0, 40, 900, ["Scalars"], ["Scalars:scalars"])],
            timelines=[queries.TimelineRecord("frame", "sequence", 0, 39 + n)],
        )
        with session_scope(catalog) as session:
            queries.save_run(session, record, t0)
    client = sql_app(tmp_path, open_store((tmp_path / "warm").as_uri()), catalog)
    runs = client.post("/v1/sql", json={"query": "SELECT * FROM runs ORDER BY id"}).json()
    assert [c["name"] for c in runs["columns"]] == [
        "id",
        "robot_id",
        "application_id",
        "date",
        "status",
        "tier",
        "started_at",
        "ended_at",
        "last_data_at",
        "sdk_version",
        "chunks",
        "rows",
        "bytes",
        "properties",
        "pinned",
        "pinned_by",
        "created_at",
        "updated_at",
    ]
    assert runs["row_count"] == 2
    run = dict(zip([c["name"] for c in runs["columns"]], runs["rows"][1], strict=True))
    assert run["id"] == "run-1" and run["date"] == "2026-03-01" and run["bytes"] == 5_000_000_001
    assert run["started_at"].startswith("2026-03-01 10:00:00") and run["pinned"] is False
    assert sql_rows(
        client,
        "SELECT id, robot_id, json_extract_string(properties, '$.fleet.site') AS site, "
        "date_diff('second', started_at, ended_at) AS took FROM runs ORDER BY id",
    ) == [
        {"id": "run-0", "robot_id": "robot-1", "site": "site-0", "took": 300},
        {"id": "run-1", "robot_id": "robot-2", "site": "site-1", "took": 300},
    ]
    assert sql_rows(client, "SELECT id, last_seen_at > created_at AS later FROM robots ORDER BY id") == [
        {"id": "robot-1", "later": True},
        {"id": "robot-2", "later": True},
    ]
    entities = sql_rows(client, "SELECT * FROM run_entities WHERE run_id = 'run-1'")
    assert entities == [
        {
            "run_id": "run-1",
            "path": "/battery",
            "chunks": 2,
            "static_chunks": 0,
            "rows": 40,
            "bytes": 900,
            "archetypes": '["Scalars"]',
            "components": '["Scalars:scalars"]',
        }
    ]
    assert sql_rows(client, "SELECT * FROM run_timelines ORDER BY run_id") == [
        {"run_id": "run-0", "name": "frame", "type": "sequence", "min": 0, "max": 39},
        {"run_id": "run-1", "name": "frame", "type": "sequence", "min": 0, "max": 40},
    ]
    assert sql_rows(
        client,
        "SELECT r.robot_id, max(t.max) AS frames FROM runs r JOIN run_timelines t "
        "ON t.run_id = r.id GROUP BY ALL ORDER BY 1",
    ) == [{"robot_id": "robot-1", "frames": 39}, {"robot_id": "robot-2", "frames": 40}]
    # no analytics file yet: the tables are there, empty, with their columns
    empty = client.post("/v1/sql", json={"query": "SELECT * FROM transforms"}).json()
    assert empty["row_count"] == 0 and {"robot_id", "date", "run_id", "entity", "tx", "qw", "log_time"} <= {
        c["name"] for c in empty["columns"]
    }


# --- answers: formats --------------------------------------------------------------------------

QUERY = (
    "SELECT robot_id, date, run_id, frame, value, log_time FROM scalars WHERE run_id = 'robot-2-2026-03-02-1' "
    "ORDER BY frame"
)
EXPECTED = [
    ("robot-2", "2026-03-02", "robot-2-2026-03-02-1", i, 2.0 + i, f"2026-03-01 00:00:00.00000000{i}") for i in range(3)
]


def test_formats_by_accept_and_by_parameter(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path):
    client = sql_app(tmp_path, local, blank)
    answer = post(client, QUERY)
    assert answer.headers["content-type"].startswith("application/json") and answer.headers["x-row-count"] == "3"
    body = answer.json()
    assert [(c["name"], c["type"]) for c in body["columns"]] == [
        ("robot_id", "string"),
        ("date", "date32[day]"),
        ("run_id", "string"),
        ("frame", "int64"),
        ("value", "double"),
        ("log_time", "timestamp[ns]"),
    ]
    assert [tuple(r) for r in body["rows"]] == EXPECTED and body["row_count"] == 3  # nanoseconds kept

    csv = post(client, QUERY, headers={"Accept": "text/csv"})
    assert csv.headers["content-type"].startswith("text/csv")
    lines = csv.text.strip().splitlines()
    assert lines[0].replace('"', "") == "robot_id,date,run_id,frame,value,log_time"
    as_text = pacsv.ConvertOptions(column_types={"date": pa.string(), "log_time": pa.string()})
    parsed = pacsv.read_csv(io.BytesIO(csv.content), convert_options=as_text)
    assert [tuple(row.values()) for row in parsed.to_pylist()] == EXPECTED

    arrow = post(client, QUERY, headers={"Accept": "application/vnd.apache.arrow.stream"})
    assert arrow.headers["content-type"] == "application/vnd.apache.arrow.stream"
    table = pa.ipc.open_stream(arrow.content).read_all()
    assert table.schema.field("log_time").type == pa.timestamp("ns") and table.schema.field("date").type == pa.date32()
    assert table["log_time"].cast(pa.int64()).to_pylist() == [START_2026_03_01_NS + i for i in range(3)]
    assert table["value"].to_pylist() == [2.0, 3.0, 4.0]

    parquet = post(client, QUERY, headers={"Accept": "application/vnd.apache.parquet"})
    assert parquet.headers["content-type"] == "application/vnd.apache.parquet"
    assert pq.read_table(pa.BufferReader(parquet.content)).equals(table)

    for fmt, media in (
        ("csv", "text/csv"),
        ("arrow", "application/vnd.apache.arrow.stream"),
        ("parquet", "application/vnd.apache.parquet"),
        ("json", "application/json"),
    ):
        chosen = post(client, QUERY, params={"format": fmt}, headers={"Accept": "text/csv; q=0.9, */*"})
        assert chosen.status_code == 200 and chosen.headers["content-type"].startswith(media), fmt
    assert post(client, QUERY, params={"format": "csv"}, headers={"Accept": "application/json"}).text == csv.text
    bad = post(client, QUERY, params={"format": "xml"})
    assert bad.status_code == 422 and bad.json()["code"] == "INVALID_ARGUMENT" and "xml" in bad.json()["message"]


def test_json_numbers_stay_numbers(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path):
    """sum() of integers is a HUGEINT in DuckDB (a decimal in Arrow): JSON must still say 42, not "42"."""
    client = sql_app(tmp_path, local, blank)
    assert sql_rows(client, "SELECT count(*) AS files, sum(frame) AS frames, avg(value) AS mean FROM scalars") == [
        {"files": 36, "frames": 36, "mean": 2.5}
    ]


@pytest.mark.slow
def test_nested_values_never_fail_the_server(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path):
    client = sql_app(tmp_path, local, blank, raise_server_exceptions=False)
    query = (
        "SELECT run_id, list(value ORDER BY frame) AS series FROM scalars WHERE run_id = 'robot-1-2026-03-01-0' "
        "GROUP BY run_id"
    )
    assert sql_rows(client, query) == [{"run_id": "robot-1-2026-03-01-0", "series": [1.0, 2.0, 3.0]}]
    csv = post(client, query, params={"format": "csv"})
    assert csv.status_code != 500, csv.text  # written as text, or refused with a clear 400
    if csv.status_code == 400:
        assert csv.json()["code"] in ("INVALID_SQL", "INVALID_ARGUMENT")


# --- limits and errors -------------------------------------------------------------------------


def test_row_limit(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path):
    client = sql_app(tmp_path, local, blank, limits=Limits(rows=36))
    assert len(sql_rows(client, "SELECT * FROM scalars")) == 36  # exactly at the limit
    assert sql_rows(client, "SELECT count(*) AS n FROM range(1000000)") == [{"n": 1_000_000}]
    too_many = post(client, "SELECT * FROM range(37)")
    assert too_many.status_code == 413, too_many.text
    assert too_many.json()["code"] == "RESULT_TOO_LARGE"
    assert "more than 36 rows" in too_many.json()["message"] and "LIMIT" in too_many.json()["message"]


def test_time_limit(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path):
    client = sql_app(tmp_path, local, blank, limits=Limits(seconds=0.5))
    started = time.monotonic()
    slow = post(client, "SELECT sum(a.range * b.range) FROM range(200000) a CROSS JOIN range(200000) b")
    assert slow.status_code == 408, slow.text
    assert time.monotonic() - started < 10
    assert slow.json()["code"] == "QUERY_TIMEOUT" and "0.5 s" in slow.json()["message"]
    assert sql_rows(client, "SELECT count(*) AS n FROM scalars") == [{"n": 36}]  # the next query runs


def test_invalid_sql(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path):
    client = sql_app(tmp_path, local, blank)
    for query, needle in (
        ("SELEC 1", "syntax error"),
        ("SELECT nope FROM scalars", "nope"),
        ("SELECT * FROM no_such_table", "no_such_table"),
    ):
        answer = post(client, query)
        assert answer.status_code == 400 and answer.json()["code"] == "INVALID_SQL", query
        assert needle in answer.json()["message"], answer.json()


# --- the sandbox -------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    ("query", "rule"),
    [
        ("CREATE TABLE t AS SELECT * FROM scalars", READ_ONLY),
        ("INSERT INTO robots VALUES ('robot-x', now(), now())", READ_ONLY),
        ("COPY (SELECT * FROM scalars) TO '{tmp}/copied.csv'", READ_ONLY),
        ("ATTACH '{tmp}/other.duckdb' AS other", READ_ONLY),
        ("INSTALL httpfs", READ_ONLY),
        ("LOAD httpfs", READ_ONLY),
        ("SET enable_external_access = true", READ_ONLY),
        ("PRAGMA enable_profiling", READ_ONLY),
        ("SELECT 1; SELECT 2", "one statement per query"),
        ("SELECT * FROM read_csv('/etc/passwd')", ALLOWED_ONLY),
        ("SELECT * FROM read_parquet('{tmp}/outside.parquet')", ALLOWED_ONLY),
        ("SELECT * FROM read_parquet('{tmp}/warm/analytics/../outside.parquet')", ALLOWED_ONLY),
        ("SELECT * FROM glob('/*')", ALLOWED_ONLY),
        ("SELECT * FROM read_text('http://127.0.0.1:9/x')", ALLOWED_ONLY),
    ],
)
def test_sandbox_refuses(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path, query: str, rule: str):
    pq.write_table(pa.table({"secret": [1]}), tmp_path / "outside.parquet")
    local.put("outside.parquet", (tmp_path / "outside.parquet").read_bytes())  # in the warm store, not analytics
    answer = post(sql_app(tmp_path, local, blank), query.format(tmp=tmp_path))
    assert answer.status_code == 400, answer.text
    assert answer.json()["code"] == "SQL_NOT_ALLOWED" and rule in answer.json()["message"], answer.json()
    assert not (tmp_path / "copied.csv").exists() and not (tmp_path / "other.duckdb").exists()


@pytest.mark.slow
@pytest.mark.parametrize("explain", ["EXPLAIN ANALYZE", "EXPLAIN (ANALYZE, FORMAT json)"])
def test_explain_analyze_cannot_write(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path, explain: str):
    """EXPLAIN ANALYZE runs the statement it explains: a COPY under it must be refused like a bare COPY
    (else a query plants rows in the analytics tables, which the sandbox lets DuckDB write to)."""
    client = sql_app(tmp_path, local, blank)
    partition = tmp_path / "warm" / "analytics" / "scalars" / "robot_id=robot-1" / "date=2026-03-01"
    planted = partition / "planted.parquet"
    answer = post(
        client,
        f"{explain} COPY (SELECT 'planted' AS run_id, '/battery' AS entity, "
        f"1e9::DOUBLE AS value) TO '{planted}' (FORMAT parquet)",
    )
    assert not planted.exists(), "a query wrote into the analytics tables"
    assert answer.status_code == 400 and answer.json()["code"] == "SQL_NOT_ALLOWED", answer.text
    assert sql_rows(client, "SELECT max(value) AS top FROM scalars") == [{"top": 4.0}]


# --- the files the catalog lists, and nothing of the server's in any answer ---------------------


@ON_BOTH_CATALOGS
def test_only_the_files_the_catalog_lists_count(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path):
    """One copy per run, gone with the run: an orphan file (a crash before the catalog recorded it),
    an early extraction filed under another robot and date, and a deleted run's file are not read."""
    client = sql_app(tmp_path, local, blank)
    assert sql_rows(client, "SELECT count(*) AS n, max(value) AS top FROM scalars") == [{"n": 36, "top": 4.0}]
    write_scalars(local, "robot-1", "2026-03-01", "orphan-run", [100.0])
    write_scalars(local, "unknown-robot", "2026-02-28", "robot-1-2026-03-01-0", [1.0, 2.0, 3.0])
    with session_scope(blank) as session:
        session.execute(sa.update(Run).where(Run.id == "robot-2-2026-03-02-1").values(tier="deleted"))
    assert sql_rows(
        client,
        "SELECT count(*) AS n, count(DISTINCT run_id) AS runs, max(value) AS top, "
        "count(*) FILTER (WHERE robot_id = 'unknown-robot') AS early FROM scalars",
    ) == [{"n": 33, "runs": 11, "top": 4.0, "early": 0}]
    assert sql_rows(client, "SELECT count(*) AS n FROM scalars WHERE run_id = 'robot-2-2026-03-02-1'") == [{"n": 0}]


SHOWS_THE_SERVER = [
    "SELECT * FROM duckdb_settings()",
    "SELECT * FROM duckdb_settings",
    "SELECT * FROM duckdb_secrets()",
    "SELECT * FROM duckdb_extensions()",
    "SELECT * FROM duckdb_views()",
    "SELECT sql FROM duckdb_views",
    "SELECT * FROM duckdb_databases()",
    "SELECT * FROM duckdb_temporary_files()",
    "SELECT * FROM pragma_version()",
    "SELECT * FROM information_schema.tables",
    "SELECT * FROM sqlite_master",
    "SELECT current_setting('home_directory') AS v",
    "SELECT current_setting('temp_directory') AS v",
    "SELECT current_setting('extension_directory') AS v",
    "SELECT current_setting('allowed_paths') AS v",
    "SELECT current_setting('s3_secret_access_key') AS v",
    "SELECT getenv('HOME') AS v",
    "SELECT getvariable('x') AS v",
    "SELECT * FROM which_secret('s3://x/y', 's3')",
    "SELECT * FROM query('SELECT current_setting(''home_directory'')')",
    "WITH s AS (SELECT current_setting('home_directory') AS v) SELECT * FROM s",
    "SELECT * FROM scalars WHERE run_id IN (SELECT sql FROM duckdb_views())",
    "EXPLAIN SELECT current_setting('home_directory')",
    "SELECT * FROM glob('*')",
    "SELECT * FROM 'warm/analytics/scalars/robot_id=robot-1/date=2026-03-01/robot-1-2026-03-01-0.parquet'",
]


@pytest.mark.slow
@pytest.mark.parametrize("query", SHOWS_THE_SERVER)
def test_nothing_shows_settings_environment_or_paths(
    local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path, query: str
):
    answer = post(sql_app(tmp_path, local, blank), query)
    assert answer.status_code == 400 and answer.json()["code"] in ("SQL_NOT_ALLOWED", "INVALID_SQL"), answer.text
    assert answer.json()["code"] == "SQL_NOT_ALLOWED" or "getvariable" not in query
    for server_string in (str(tmp_path), str(Path.home()), "pytest-of"):
        assert server_string not in answer.text


@pytest.mark.slow
def test_plans_and_errors_name_no_server_path(local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path):
    client = sql_app(tmp_path, local, blank)
    for explain in ("EXPLAIN ANALYZE", "EXPLAIN", "EXPLAIN (FORMAT json)", "EXPLAIN (ANALYZE, FORMAT json)"):
        plan = post(client, f"{explain} SELECT * FROM scalars WHERE robot_id = 'robot-1'")
        assert plan.status_code == 200, plan.text
        for server_string in (str(tmp_path), "/tmp", "pytest", "warm/"):
            assert server_string not in plan.text, (explain, server_string)
    assert files_read(client, "SELECT count(*) FROM scalars") == 12
    (
        tmp_path
        / "warm"
        / "analytics"
        / "scalars"
        / "robot_id=robot-3"
        / "date=2026-03-02"
        / "robot-3-2026-03-02-1.parquet"
    ).unlink()  # listed by the catalog, gone from the store
    broken = post(client, "SELECT count(*) FROM scalars")
    assert broken.status_code == 503 and broken.json()["code"] == "UNAVAILABLE", broken.text
    assert "scalars" in broken.json()["message"] and str(tmp_path) not in broken.text and "pytest" not in broken.text


# --- partition pruning -------------------------------------------------------------------------


@pytest.mark.slow
@ON_BOTH_CATALOGS
def test_filters_on_robot_and_date_read_only_those_partitions(
    local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path
):
    client = sql_app(tmp_path, local, blank)
    assert files_read(client, "SELECT count(*) FROM scalars") == 12
    assert files_read(client, "SELECT count(*) FROM scalars WHERE robot_id = 'robot-2'") == 4
    assert files_read(client, "SELECT count(*) FROM scalars WHERE date = DATE '2026-03-02'") == 6
    both = "SELECT count(*) AS n, sum(value) AS total FROM scalars WHERE robot_id = 'robot-2' AND date = '2026-03-02'"
    assert files_read(client, both) == 2
    assert sql_rows(client, both) == [{"n": 6, "total": 6.0 + 9.0}]


@pytest.mark.slow
@ON_BOTH_CATALOGS
def test_through_the_lakehouse_answers_and_pruning_are_the_same(
    local: ObjectStore, blank: sessionmaker[Session], tmp_path: Path
):
    """The same files copied into the lakehouse's Iceberg tables (as `fleet analytics migrate` does):
    SQL reads their data files, one per run, and skips other robots' and days' folders as before."""
    from catalog import lakehouse as marks
    from services.lakehouse.sync import sync
    from services.lakehouse.tables import open_lakehouse

    before = sql_rows(sql_app(tmp_path / "per-run", local, blank), "SELECT * FROM scalars ORDER BY run_id, frame")
    url = blank.kw["bind"].url.render_as_string(hide_password=False)
    lake = open_lakehouse(url, local)
    try:
        with session_scope(blank, write=True) as session:
            assert marks.queue_all(session) == 12
        assert sync(lake, blank, local, lambda: dt.datetime.now(dt.UTC)).runs == 12
        node = node_of(tmp_path, blank, tiers=Tiers(local, local), lakehouse=lake)
        client = TestClient(create_app(node, analytics=opened(Analytics(node, Limits()))))
        after = sql_rows(client, "SELECT * FROM scalars ORDER BY run_id, frame")
        assert [{k: v for k, v in row.items() if k != "log_time_ns"} for row in after] == before
        assert files_read(client, "SELECT count(*) FROM scalars") == 12
        assert files_read(client, "SELECT count(*) FROM scalars WHERE robot_id = 'robot-2'") == 4
        assert files_read(client, "SELECT count(*) FROM scalars WHERE date = DATE '2026-03-02'") == 6
        # the Iceberg metadata is the server's to read: never reachable from a query, never named
        metadata = lake.table("scalars").metadata_location
        for query in (f"SELECT * FROM iceberg_scan('{metadata}')", f"SELECT * FROM read_json('{metadata}')"):
            refused = post(client, query)
            assert refused.status_code == 400 and refused.json()["code"] == "SQL_NOT_ALLOWED", refused.text
        plan = post(client, "EXPLAIN ANALYZE SELECT count(*) FROM scalars WHERE robot_id = 'robot-2'")
        assert plan.status_code == 200 and "lakehouse" not in plan.text and str(tmp_path) not in plan.text
    finally:
        lake.close()


# --- over S3: a real server (SeaweedFS) ---------------------------------------------------------


@pytest.fixture(scope="module")
def seaweed_endpoint(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    with seaweedfs(tmp_path_factory.mktemp("seaweedfs")) as endpoint:
        boto3.client(
            "s3", endpoint_url=endpoint, region_name="us-east-1", aws_access_key_id="test", aws_secret_access_key="test"
        ).create_bucket(Bucket=BUCKET)  # one bucket, a prefix per test
        yield endpoint


@pytest.fixture
def on_s3(
    seaweed_endpoint: str, blank: sessionmaker[Session], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[tuple[TestClient, ObjectStore]]:
    """A warm store on S3 with the credentials in AWS_* (where DuckDB's httpfs also looks), and
    objects outside its analytics folder: elsewhere in its prefix, another prefix, another bucket."""
    for name, value in (
        ("AWS_ACCESS_KEY_ID", KEY_ID),
        ("AWS_SECRET_ACCESS_KEY", SECRET),
        ("AWS_DEFAULT_REGION", "us-east-1"),
    ):
        monkeypatch.setenv(name, value)
    store = open_store(f"s3://{BUCKET}/{tmp_path.name}", endpoint_url=seaweed_endpoint, region="us-east-1")
    fill(store, blank)
    store.put("outside/notes.csv", b"secret\n1\n")
    neighbour = open_store(f"s3://{BUCKET}/{tmp_path.name}-other", endpoint_url=seaweed_endpoint, region="us-east-1")
    write_scalars(neighbour, "robot-9", "2026-03-01", "neighbour-run", [1.0])
    s3 = boto3.client(
        "s3",
        endpoint_url=seaweed_endpoint,
        region_name="us-east-1",
        aws_access_key_id=KEY_ID,
        aws_secret_access_key=SECRET,
    )
    with contextlib.suppress(s3.exceptions.BucketAlreadyOwnedByYou, s3.exceptions.BucketAlreadyExists):
        s3.create_bucket(Bucket=OTHER_BUCKET)
    s3.put_object(Bucket=OTHER_BUCKET, Key="private/notes.csv", Body=b"secret\n1\n")
    yield sql_app(tmp_path, store, blank), store


KEY_ID, SECRET, OTHER_BUCKET = "fleet-test-key", "fleet-test-secret-6c1f", "fleet-other"


@pytest.mark.slow
@pytest.mark.s3server
def test_over_s3(on_s3: tuple[TestClient, ObjectStore]):
    client, _ = on_s3
    assert sql_rows(
        client, "SELECT robot_id, count(*) AS n, sum(value) AS total FROM scalars GROUP BY 1 ORDER BY 1"
    ) == [{"robot_id": r, "n": 12, "total": 30.0} for r in ROBOTS]
    assert files_read(client, "SELECT count(*) FROM scalars") == 12
    assert files_read(client, "SELECT count(*) FROM scalars WHERE robot_id = 'robot-3' AND date = '2026-03-01'") == 2
    arrow = post(client, "SELECT * FROM scalars WHERE robot_id = 'robot-1'", params={"format": "arrow"})
    assert pa.ipc.open_stream(arrow.content).read_all().num_rows == 12


@pytest.mark.slow
@pytest.mark.s3server
@pytest.mark.parametrize(
    "query",
    [
        "SELECT current_setting('s3_secret_access_key') AS v",
        "SELECT current_setting('s3_access_key_id') AS v",
        "SELECT current_setting('s3_endpoint') AS v",
        "SELECT * FROM duckdb_secrets()",
        "SELECT * FROM duckdb_settings()",
        "SELECT getenv('AWS_SECRET_ACCESS_KEY') AS v",
        "SELECT * FROM which_secret('s3://{bucket}/x', 's3')",
        "EXPLAIN ANALYZE SELECT * FROM scalars",
        "SELECT * FROM duckdb_views()",
    ],
)
def test_no_answer_over_s3_reveals_credentials_or_where_the_store_is(
    on_s3: tuple[TestClient, ObjectStore], tmp_path: Path, query: str
):
    client, _ = on_s3
    answer = post(client, query.format(bucket=BUCKET))
    assert answer.status_code in (200, 400), answer.text
    for server_string in (SECRET, KEY_ID, f"{BUCKET}/{tmp_path.name}", "127.0.0.1"):
        assert server_string not in answer.text, server_string


@pytest.mark.slow
@pytest.mark.s3server
@pytest.mark.parametrize(
    "path",
    [
        "{prefix}/outside/notes.csv",  # the warm store, outside analytics
        "{prefix}/analytics/../outside/notes.csv",
        "{prefix}/analytics/../../{prefix}-other/analytics/scalars/robot_id=robot-9/date=2026-03-01/neighbour-run.parquet",
        "{prefix}/analytics/../../../{other}/private/notes.csv",  # another bucket
        "{prefix}/analytics/scalars/../../../../{other}/private/notes.csv",
    ],
)
def test_no_query_reads_outside_the_analytics_folder(on_s3: tuple[TestClient, ObjectStore], tmp_path: Path, path: str):
    client, _ = on_s3
    url = f"s3://{BUCKET}/" + path.format(prefix=tmp_path.name, other=OTHER_BUCKET)
    reader = "read_parquet" if url.endswith(".parquet") else "read_csv"
    for query in (
        f"SELECT * FROM {reader}('{url}')",
        f"SELECT * FROM '{url}'",
        f"SELECT * FROM scalars WHERE run_id IN (SELECT * FROM {reader}('{url}'))",
    ):
        refused = post(client, query)
        assert refused.status_code == 400 and refused.json()["code"] == "SQL_NOT_ALLOWED", (query, refused.text)
        assert "rows" not in refused.json()


# --- `fleet sql` and the Python client against `fleet serve` ----------------------------------

LIVE_RUN, LIVE_ROBOT = "live-sql-run", "robot-live"
LIVE_SCRIPT = """
rec = recording(FOLDER + "/live.rrd", {run!r}, {robot!r}, {start})
for i in range(4):
    rec.set_time("frame", sequence=i)
    rec.log("/battery", rr.Scalars(90.0 - 2.5 * i))
    rec.log("/logs", rr.TextLog(f"step {{i}}", level="ERROR" if i == 2 else "INFO"))
finish(rec)
"""


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    folder = tmp_path_factory.mktemp("analytics-live")
    log_with_sdk(
        f"FOLDER = {str(folder)!r}\n" + LIVE_SCRIPT.format(run=LIVE_RUN, robot=LIVE_ROBOT, start=START_2026_03_01_NS)
    )
    server = LiveServer(folder / "data", sql_max_rows="100").start()
    try:
        uploaded = httpx.post(f"{server.url}/v1/uploads", content=(folder / "live.rrd").read_bytes(), timeout=60)
        assert uploaded.status_code == 200, uploaded.text
        assert httpx.post(f"{server.url}/v1/runs/{LIVE_RUN}/analytics", timeout=60).status_code == 200
        yield server
    finally:
        server.stop()


def fleet_sql(server: LiveServer, *args: str) -> subprocess.CompletedProcess[bytes]:
    return subprocess.run([FLEET, "sql", *args, "--api-url", server.url], capture_output=True, timeout=120)


@pytest.mark.sdk
def test_fleet_sql_cli(live: LiveServer, tmp_path: Path):
    query = (
        "SELECT r.robot_id, count(*) AS errors FROM text_logs t JOIN runs r ON r.id = t.run_id "
        "WHERE level = 'ERROR' GROUP BY 1"
    )
    table = fleet_sql(live, query)
    assert table.returncode == 0, table.stderr
    assert re.search(rf"{LIVE_ROBOT}\s+1\b", table.stdout.decode()) and b"(1 rows)" in table.stderr
    csv = fleet_sql(live, "--format", "csv", "SELECT frame, value FROM scalars ORDER BY frame")
    assert csv.returncode == 0 and csv.stdout.decode().split() == [
        '"frame","value"',
        "0,90",
        "1,87.5",
        "2,85",
        "3,82.5",
    ]
    out = tmp_path / "answer.parquet"
    written = fleet_sql(live, "--format", "parquet", "-o", str(out), "SELECT * FROM scalars")
    assert written.returncode == 0 and pq.read_table(out).num_rows == 4
    refused = fleet_sql(live, "DROP VIEW runs")
    assert refused.returncode == 1 and b"DROP is not allowed" in refused.stderr
    assert len(refused.stderr.decode().strip().splitlines()) == 1  # one line, no traceback


@pytest.mark.sdk
def test_python_client_returns_a_pyarrow_table(live: LiveServer):
    with FleetClient(live.url) as client:
        table = client.sql("SELECT s.*, r.tier FROM scalars s JOIN runs r ON r.id = s.run_id ORDER BY frame")
        assert isinstance(table, pa.Table) and table.num_rows == 4
        assert table.schema.field("date").type == pa.date32()
        assert table.schema.field("log_time").type == pa.timestamp("ns")
        assert table["value"].to_pylist() == [90.0, 87.5, 85.0, 82.5]
        assert set(table["robot_id"].to_pylist()) == {LIVE_ROBOT} and set(table["tier"].to_pylist()) == {"hot"}
        assert client.sql_bytes("SELECT count(*) AS n FROM text_logs", "csv").split() == [b'"n"', b"4"]
        as_json = json.loads(client.sql_bytes("SELECT DISTINCT robot_id, date FROM scalars", "json"))
        assert as_json["rows"] == [[LIVE_ROBOT, "2026-03-01"]]
        with pytest.raises(ServiceError) as too_many:  # FLEET_SQL_MAX_ROWS=100 for this server
            client.sql("SELECT * FROM range(101)")
        assert too_many.value.status == 413 and "more than 100 rows" in str(too_many.value)
        with pytest.raises(ServiceError) as refused:
            client.sql("SELECT * FROM read_csv('/etc/passwd')")
        assert refused.value.status == 400 and refused.value.code.value == "SQL_NOT_ALLOWED"
