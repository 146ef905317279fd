"""Loading `benchmarks/catalog_scale_fill.py`'s fleet into a migrated catalog in bulk: Postgres by
`COPY ... FROM STDIN (FORMAT csv)` from Arrow tables written as CSV, DuckDB by `INSERT ... SELECT`
from the same Arrow tables registered on its connection; then the tables that do not grow with the
runs (robots, datasets, rules versions, a month of job runs, pulls, a dataset snapshot)."""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import sqlalchemy as sa
from sqlalchemy.orm import Session

from benchmarks.catalog_scale_fill import (
    APPLICATIONS,
    CHUNK_RUNS,
    ROBOTS,
    RULES_VERSION,
    SNAPSHOT,
    SNAPSHOT_EPISODES,
    Fleet,
    chunk_tables,
    make_chunk,
    robot_name,
)
from catalog import dataset_columns
from catalog.models import DatasetEpisode
from catalog.queries import insert_rows
from core.ids import new_entry_id

CSV = pacsv.WriteOptions(include_header=False, batch_size=65_536)
JOB_DAYS = 30  # the catalog keeps a month of job runs (services/retention/schedule.py)
PULLS = 2_000

Progress = Callable[[str], None]


def load_table(connection: sa.Connection, name: str, table: pa.Table) -> None:
    """Rows into `name`, in bulk, on whichever catalog `connection` is."""
    if table.num_rows == 0:
        return
    raw: Any = connection.connection.driver_connection
    columns = ", ".join(f'"{column}"' for column in table.column_names)
    if connection.dialect.name == "duckdb":
        raw.register("fleet_scale_rows", table)
        try:
            raw.execute(f'INSERT INTO "{name}" ({columns}) SELECT {columns} FROM fleet_scale_rows')
        finally:
            raw.unregister("fleet_scale_rows")
        return
    buffer = io.BytesIO()
    pacsv.write_csv(table, buffer, CSV)
    with raw.cursor() as cursor, cursor.copy(f'COPY "{name}" ({columns}) FROM STDIN (FORMAT csv)') as copy:
        copy.write(buffer.getbuffer())


class RobotSpan:
    """Each robot's first run start and last data, for its row."""

    def __init__(self) -> None:
        self.first = np.full(ROBOTS, np.iinfo(np.int64).max)
        self.last = np.zeros(ROBOTS, dtype=np.int64)

    def add(self, robots: np.ndarray, start_ns: np.ndarray, end_ns: np.ndarray) -> None:
        np.minimum.at(self.first, robots, start_ns)
        np.maximum.at(self.last, robots, end_ns)


def fill(engine: sa.Engine, fleet: Fleet, progress: Progress) -> dict[str, float]:
    """Load the whole fleet; seconds spent per table (generation included)."""
    seconds: dict[str, float] = defaultdict(float)
    span = RobotSpan()
    newest: pa.Table | None = None
    for lo in range(0, fleet.runs, CHUNK_RUNS):
        hi = min(fleet.runs, lo + CHUNK_RUNS)
        started = time.perf_counter()
        chunk = make_chunk(fleet, lo, hi)
        span.add(chunk.robot, chunk.start_ns, chunk.end_ns)
        with engine.begin() as connection:
            for name, table in chunk_tables(fleet, chunk):
                load_table(connection, name, table)
                seconds[name] += time.perf_counter() - started
                started = time.perf_counter()
                newest = table if name == "events" else newest
        progress(f"  runs {hi:,} of {fleet.runs:,}")
    started = time.perf_counter()
    with engine.begin() as connection:
        for name, table in fixed_tables(fleet, span).items():
            load_table(connection, name, table)
        if newest is not None:
            load_snapshot(connection, fleet, newest)
    seconds["others"] = time.perf_counter() - started
    started = time.perf_counter()
    progress("  dataset columns (counted from the runs, as `fleet db upgrade` does)")
    with Session(engine) as session, session.begin():
        dataset_columns.refill(session)
    seconds["dataset_columns"] = time.perf_counter() - started
    return dict(seconds)


def _utc(ns: np.ndarray) -> pa.Array:
    return pa.array(np.asarray(ns, dtype=np.int64) // 1000, type=pa.timestamp("us", tz="UTC"))


def fixed_tables(fleet: Fleet, span: RobotSpan) -> dict[str, pa.Table]:
    year_ago = fleet.now_ns - 365 * 86_400 * 10**9
    robots = pa.table(
        {"id": [robot_name(r) for r in range(ROBOTS)], "created_at": _utc(span.first), "last_seen_at": _utc(span.last)}
    )
    datasets = pa.table(
        {
            "name": list(APPLICATIONS),
            "entry_id": [new_entry_id(name, year_ago) for name in APPLICATIONS],
            "created_at": _utc(np.full(len(APPLICATIONS), year_ago)),
            "updated_at": _utc(np.full(len(APPLICATIONS), fleet.now_ns)),
        }
    )
    return {
        "robots": robots,
        "datasets": datasets,
        "rules_versions": rules_versions(fleet),
        "job_runs": job_runs(fleet),
    }


def rules_versions(fleet: Fleet) -> pa.Table:
    texts = [f"# the rules file, version {n}\n" for n in range(1, RULES_VERSION + 1)]
    return pa.table(
        {
            "version": list(range(1, RULES_VERSION + 1)),
            "text": texts,
            "digest": [hashlib.sha256(text.encode()).hexdigest() for text in texts],
            "created_by": ["alice"] * RULES_VERSION,
            "created_at": _utc(fleet.now_ns - np.arange(RULES_VERSION, 0, -1) * 30 * 86_400 * 10**9),
        }
    )


def job_runs(fleet: Fleet) -> pa.Table:
    """A month of the schedule: promotion every minute, retention every hour; a few failed."""
    month_ago = fleet.now_ns - JOB_DAYS * 86_400 * 10**9
    promote = np.arange(month_ago, fleet.now_ns, 60 * 10**9)
    retention = np.arange(month_ago, fleet.now_ns, 3600 * 10**9)
    starts = np.concatenate([promote, retention])
    jobs = np.repeat(np.array(["promote", "retention"], dtype=object), [len(promote), len(retention)])
    failed = np.random.default_rng([fleet.seed, 1]).random(len(starts)) < 0.005
    return pa.table(
        {
            "id": [f"{n:032x}" for n in range(len(starts))],
            "job": jobs,
            "node": np.full(len(starts), "node-1", dtype=object),
            "started_at": _utc(starts),
            "finished_at": _utc(starts + 400_000_000),
            "outcome": np.where(failed, "failed", "ok").astype(object),
            "detail": np.where(failed, "OSError: the warm store did not answer", "3 done, 0 failed").astype(object),
        }
    )


def load_snapshot(connection: sa.Connection, fleet: Fleet, events: pa.Table) -> None:
    """Pulls of recent runs, and snapshot `interventions@1`: a window around each of the newest
    chunk's first intervention events."""
    interventions = events.filter(pc.equal(events.column("kind"), "intervention"))
    picked = interventions.slice(0, SNAPSHOT_EPISODES).to_pylist()
    now = dt.datetime.fromtimestamp(fleet.now_ns / 1e9, dt.UTC)
    load_table(connection, "pulls", pulls(fleet, events.slice(0, PULLS).to_pylist(), now))
    load_table(
        connection, "dataset_snapshots", pa.table({"name": [SNAPSHOT], "created_by": ["alice"], "created_at": [now]})
    )
    version = {
        "name": [SNAPSHOT],
        "version": [1],
        "selection": ['{"event": ["intervention"]}'],
        "created_by": ["alice"],
        "created_at": [now],
        "rules_version": [RULES_VERSION],
        "episodes": [len(picked)],
        "runs": [len({e["run_id"] for e in picked})],
        "chunks": [len(picked) * 40],
        "bytes": [len(picked) * 40 * 30_000],
        "skipped": ["[]"],
    }
    load_table(connection, "dataset_versions", pa.table(version))
    rows = [
        {
            "name": SNAPSHOT,
            "version": 1,
            "episode": n,
            "run_id": e["run_id"],
            "robot_id": e["robot_id"],
            "split": "train" if n % 10 else "validation",
            "timeline": "log_time",
            "range_start": e["range_start"] - 5 * 10**9,
            "range_end": e["range_end"] + 5 * 10**9,
            "event_id": e["id"],
            "chunk_ids": bytes(range(16)) * 40,
            "chunks": 40,
            "bytes": 40 * 30_000,
        }
        for n, e in enumerate(picked)
    ]
    insert_rows(Session(bind=connection), DatasetEpisode, rows)


def pulls(fleet: Fleet, events: list[dict[str, Any]], now: dt.datetime) -> pa.Table:
    count = len(events)
    return pa.table(
        {
            "id": [f"pull-{n:012x}" for n in range(count)],
            "run_id": [e["run_id"] for e in events],
            "robot_id": [e["robot_id"] for e in events],
            "include": ['["/camera/**"]'] * count,
            "exclude": ["[]"] * count,
            "state": ["done"] * count,
            "requested_by": ["alice"] * count,
            "requested_at": [now] * count,
            "updated_at": [now] * count,
            "chunks_sent": [400] * count,
            "bytes_sent": [12_000_000] * count,
            "origin": ["person"] * count,
            "event_id": [e["id"] for e in events],
            "priority": pa.nulls(count, pa.string()),
        }
    )


def finish(engine: sa.Engine, progress: Progress) -> float:
    """What an operator's catalog has after a bulk load: statistics, and on Postgres a vacuumed
    visibility map (so index-only scans skip the heap); seconds taken."""
    started = time.perf_counter()
    if engine.dialect.name == "duckdb":
        with engine.begin() as connection:
            connection.exec_driver_sql("CHECKPOINT")
    else:
        progress("  VACUUM (ANALYZE)")
        with engine.connect().execution_options(isolation_level="AUTOCOMMIT") as connection:
            connection.exec_driver_sql("VACUUM (ANALYZE)")
    return time.perf_counter() - started
