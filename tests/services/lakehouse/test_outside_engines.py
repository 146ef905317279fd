"""The lakehouse as analysts reach it: runs logged with the real SDK, uploaded to `fleet serve` on
SeaweedFS and Postgres (auth on) and sealed; then, from a venv of their own with credentials of their
own (a read-only database role, a bucket key that reads the lakehouse prefix only), pyiceberg and
DuckDB see in `fleet.scalars` and `fleet.text_logs` exactly the rows `POST /v1/sql` counts, and in
`fleet.runs` the runs. Deleting a run takes its rows out of every table; the analyst's key reads no
recording and its role writes nothing."""

from __future__ import annotations

import json
import subprocess
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import sqlalchemy as sa

from catalog.db import create_engine
from catalog.db import upgrade as upgrade_catalog
from tests.compat.lakehouse_venv import lakehouse_python
from tests.postgres import admin_engine
from tests.seaweedfs import SIGNED_ONLY_ACCESS_KEY, SIGNED_ONLY_SECRET_KEY, SeaweedFS
from tests.services.analytics.conftest import log_with_sdk
from tests.services.ingest.live_server import LiveServer

pytestmark = [pytest.mark.sdk, pytest.mark.slow, pytest.mark.s3server, pytest.mark.postgres]

BUCKET, PREFIX = "fleet-lake", "depot"
ANALYST_KEY, ANALYST_SECRET = "analyst", "analyst-secret-of-the-lake-tests"
ANALYST = {  # reads the lakehouse prefix, lists the bucket: the bucket policy docs/lakehouse.md gives
    "name": "analyst",
    "credentials": [{"accessKey": ANALYST_KEY, "secretKey": ANALYST_SECRET}],
    "actions": [f"Read:{BUCKET}/{PREFIX}/lakehouse/*", f"List:{BUCKET}"],
}
RUNS = {"lake-run-1": "robot-1", "lake-run-2": "robot-2", "lake-run-3": "robot-2"}

SCRIPT = """
import json, uuid
rr_runs = json.loads({runs!r})
truth = {{}}
for i, (run, robot) in enumerate(sorted(rr_runs.items())):
    rec = recording(FOLDER + f"/{{run}}.rrd", run, robot, 1_772_323_200_000_000_000 + i * 3_600_000_000_000)
    n = 20 + 10 * i
    for k in range(n):
        rec.set_time("log_time", timestamp=1_772_323_200 + i * 3600 + k * 0.1)
        rec.set_time("frame", sequence=k)
        rec.log("/battery", rr.Scalars(100.0 - k))
        rec.log("/joints", rr.Scalars([1.0 * k, 2.0 * k]))
        if k % 5 == 0:
            rec.log("/logs", rr.TextLog(f"step {{k}}", level="INFO"))
    finish(rec)
    truth[run] = {{"scalars": 3 * n, "text_logs": n // 5}}
print(json.dumps(truth))
"""

READER = r"""
import json, sys
import duckdb, duckdb_extension_avro, duckdb_extension_httpfs, duckdb_extension_iceberg
from pathlib import Path
from pyiceberg.catalog.sql import SqlCatalog

cfg = json.loads(sys.argv[1])
catalog = SqlCatalog("fleet", **{
    "uri": cfg["uri"], "init_catalog_tables": "false",
    "s3.endpoint": cfg["endpoint"], "s3.access-key-id": cfg["key"], "s3.secret-access-key": cfg["secret"],
    "s3.region": "us-east-1", "s3.force-virtual-addressing": "false",
})
out = {"pyiceberg": {}, "duckdb": {}}
con = duckdb.connect()
wheels = ((duckdb_extension_httpfs, "httpfs"), (duckdb_extension_avro, "avro"), (duckdb_extension_iceberg, "iceberg"))
for module, name in wheels:
    con.execute(f"LOAD '{next(Path(module.__file__).parent.glob('extensions/*/' + name + '.duckdb_extension'))}'")
host = cfg["endpoint"].removeprefix("http://")
con.execute(f"CREATE SECRET (TYPE s3, KEY_ID '{cfg['key']}', SECRET '{cfg['secret']}', ENDPOINT '{host}', "
            "URL_STYLE 'path', USE_SSL false, REGION 'us-east-1')")
for name in ("scalars", "text_logs", "runs"):
    table = catalog.load_table(("fleet", name))
    column = "id" if name == "runs" else "run_id"
    rows = table.scan(selected_fields=(column,)).to_arrow()[column].to_pylist()
    out["pyiceberg"][name] = {r: rows.count(r) for r in set(rows)}
    scan = f"iceberg_scan('{table.metadata_location}')"
    out["duckdb"][name] = dict(con.execute(f"SELECT {column}, count(*) FROM {scan} GROUP BY 1").fetchall())
try:
    catalog.drop_table(("fleet", "scalars"))
    out["drop"] = "dropped"
except Exception as exc:
    out["drop"] = type(exc).__name__ + ": " + str(exc).splitlines()[0]
try:
    con.execute(f"SELECT count(*) FROM read_parquet('s3://{cfg['bucket']}/{cfg['recording']}')").fetchall()
    out["recording"] = "read"
except Exception as exc:
    out["recording"] = str(exc).splitlines()[0]
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def weed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedFS]:
    server = SeaweedFS(tmp_path_factory.mktemp("lake-weed") / "data", signed_only=True, identities=(ANALYST,)).start()
    try:
        server.client().create_bucket(Bucket=BUCKET)
        yield server
    finally:
        server.stop()


@pytest.fixture
def analyst_role(empty_postgres_url: str) -> Iterator[str]:
    """A login role of the analyst's, created on the server (roles are the server's, not a database's)."""
    name = f"fleet_analyst_{uuid.uuid4().hex[:8]}"
    admin = admin_engine()
    with admin.connect() as conn:
        conn.execute(sa.text(f'CREATE ROLE "{name}" LOGIN'))
    try:
        yield name
    finally:
        database = create_engine(empty_postgres_url)
        with database.begin() as conn:  # its grants there go first
            conn.execute(sa.text(f'DROP OWNED BY "{name}"'))
        database.dispose()
        with admin.connect() as conn:
            conn.execute(sa.text(f'DROP ROLE IF EXISTS "{name}"'))
        admin.dispose()


def grant_read(url: str, role: str) -> None:
    """What docs/lakehouse.md says to grant an analyst: read the Iceberg catalog's two tables."""
    engine = create_engine(url)
    with engine.begin() as conn:
        conn.execute(sa.text(f'GRANT USAGE ON SCHEMA public TO "{role}"'))
        conn.execute(sa.text(f'GRANT SELECT ON iceberg_tables, iceberg_namespace_properties TO "{role}"'))
    engine.dispose()


def sql_counts(server: LiveServer, table: str) -> dict[str, int]:
    query = f"SELECT run_id, count(*) AS n FROM {table} GROUP BY run_id"
    answer = httpx.post(f"{server.url}/v1/sql", json={"query": query}, headers=server.headers, timeout=60)
    assert answer.status_code == 200, answer.text
    return {run: n for run, n in answer.json()["rows"]}


def read_as_analyst(weed: SeaweedFS, uri: str, recording: str) -> dict[str, Any]:
    config = {
        "uri": uri,
        "endpoint": weed.endpoint,
        "key": ANALYST_KEY,
        "secret": ANALYST_SECRET,
        "bucket": BUCKET,
        "recording": recording,
    }
    env = {"PATH": "/usr/bin:/bin", "HOME": str(Path.home())}  # none of the depot's AWS_* or FLEET_*
    done = subprocess.run(
        [str(lakehouse_python()), "-c", READER, json.dumps(config)],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    answer: dict[str, Any] = json.loads(done.stdout.strip().splitlines()[-1])
    return answer


def test_outside_engines_read_exactly_what_sql_counts(
    tmp_path: Path, weed: SeaweedFS, empty_postgres_url: str, analyst_role: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    engine = create_engine(empty_postgres_url)
    upgrade_catalog(engine)
    engine.dispose()
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", SIGNED_ONLY_ACCESS_KEY)  # the depot's own key
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", SIGNED_ONLY_SECRET_KEY)
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    folder = tmp_path / "sdk"
    folder.mkdir()
    truth = log_with_sdk(f"FOLDER = {str(folder)!r}\n" + SCRIPT.format(runs=json.dumps(RUNS)), flush_rows=8)
    server = LiveServer(
        tmp_path / "data",
        catalog_url=empty_postgres_url,
        warm_url=f"s3://{BUCKET}/{PREFIX}",
        s3_endpoint_url=weed.endpoint,
        promote_after_s="0",
        promote_interval_s="0.2",
        lakehouse_sync_s="0.5",
    ).start()
    try:
        for run in RUNS:
            upload = httpx.post(
                f"{server.url}/v1/uploads",
                content=(folder / f"{run}.rrd").read_bytes(),
                headers=server.headers,
                timeout=60,
            )
            assert upload.status_code == 200, upload.text

        expected = {table: {run: truth[run][table] for run in RUNS} for table in ("scalars", "text_logs")}
        server.wait_for(lambda: sql_counts(server, "scalars") == expected["scalars"], 120, "every run sealed")
        assert sql_counts(server, "text_logs") == expected["text_logs"]
        grant_read(empty_postgres_url, analyst_role)
        analyst_uri = f"postgresql+psycopg2://{analyst_role}@127.0.0.1:5432/{empty_postgres_url.rsplit('/', 1)[1]}"
        detail = httpx.get(f"{server.url}/v1/runs/lake-run-1", headers=server.headers, timeout=10).json()
        recording = next(o["key"] for o in detail["objects"] if o["name"] == "recording.rrd")
        seen = read_as_analyst(weed, analyst_uri, f"{PREFIX}/{recording}")
        for engine_name in ("pyiceberg", "duckdb"):
            for table in ("scalars", "text_logs"):
                assert seen[engine_name][table] == expected[table], (engine_name, table)
            assert seen[engine_name]["runs"] == dict.fromkeys(RUNS, 1), engine_name
        assert seen["drop"].startswith(("ProgrammingError", "InsufficientPrivilege")), seen["drop"]
        assert "403" in seen["recording"] or "Access" in seen["recording"], seen["recording"]

        gone = httpx.delete(f"{server.url}/v1/runs/lake-run-2", headers=server.headers, timeout=60)
        assert gone.status_code == 200, gone.text
        left = {table: {r: n for r, n in counts.items() if r != "lake-run-2"} for table, counts in expected.items()}
        assert sql_counts(server, "scalars") == left["scalars"]
        seen = read_as_analyst(weed, analyst_uri, f"{PREFIX}/{recording}")
        for engine_name in ("pyiceberg", "duckdb"):
            for table in ("scalars", "text_logs"):
                assert seen[engine_name][table] == left[table], (engine_name, table)
    finally:
        server.stop()
