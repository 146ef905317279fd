"""Benchmark: one catalog flush of live runs (`catalog.queries.save_run` for each, one transaction),
as ingest's housekeeping writes it every FLEET_CATALOG_FLUSH_S: each run's row, and its entities and
timelines replaced.

    .venv/bin/python benchmarks/catalog_flush.py [--runs 8] [--entities 101] [--flushes 5]
        [--postgres postgresql+psycopg://postgres@127.0.0.1:5432/test]

`--postgres` names a server (through a database to connect to): the flushes run in a database of
their own there, dropped afterwards.

On the embedded DuckDB catalog it times the rows going in as one Arrow table per insert (what
`catalog.queries.insert_rows` does there) and, for comparison, by executemany (row by row in
DuckDB's driver); on Postgres (if `--postgres` is given and answers), by executemany. Prints the
median CPU seconds of a flush on this thread.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import sqlalchemy as sa  # noqa: E402
from sqlalchemy.orm import sessionmaker  # noqa: E402

from catalog import queries  # noqa: E402
from catalog.db import create_engine, session_scope, upgrade  # noqa: E402
from catalog.models import Base  # noqa: E402
from catalog.queries import EntityRecord, RunRecord, TimelineRecord  # noqa: E402


def records(runs: int, entities: int, chunks: int) -> list[RunRecord]:
    now = dt.datetime.now(dt.UTC)
    return [
        RunRecord(
            id=f"run-{i}",
            robot_id="robot-1",
            application_id="bench",
            date=now.date(),
            status="live",
            tier="hot",
            started_at=now,
            ended_at=None,
            last_data_at=now,
            sdk_version="0.41.0",
            chunks=chunks * entities,
            rows=chunks * entities,
            bytes=chunks * entities * 1200,
            properties={},
            entities=[
                EntityRecord(
                    f"/world/entity_{k}", chunks, 0, chunks, chunks * 1200, ["Points3D"], ["Points3D:positions"]
                )
                for k in range(entities)
            ],
            timelines=[
                TimelineRecord("log_time", "timestamp", 0, chunks),
                TimelineRecord("step", "sequence", 0, chunks),
            ],
        )
        for i in range(runs)
    ]


def flush_cpu(url: str, args: argparse.Namespace) -> float:
    engine = create_engine(url)
    upgrade(engine)
    factory = sessionmaker(engine)
    times = []
    for n in range(args.flushes + 1):  # the first makes the rows: not counted
        batch = records(args.runs, args.entities, n + 1)
        started = time.thread_time()
        with session_scope(factory, write=True) as session:
            for record in batch:
                queries.save_run(session, record, dt.datetime.now(dt.UTC))
        if n:
            times.append(time.thread_time() - started)
    engine.dispose()
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=8, help="live runs in a flush (default 8)")
    parser.add_argument("--entities", type=int, default=101, help="entities of each run (default 101)")
    parser.add_argument("--flushes", type=int, default=5, help="flushes timed (default 5)")
    parser.add_argument("--postgres", help="a Postgres URL to time too (its tables are created if missing)")
    args = parser.parse_args()
    rows = args.runs * args.entities
    with tempfile.TemporaryDirectory() as tmp:
        arrow = flush_cpu(f"duckdb:///{tmp}/arrow.duckdb", args)
        row_by_row = _executemany_on_duckdb(f"duckdb:///{tmp}/rows.duckdb", args)
    print(f"one flush of {args.runs} runs x {args.entities} entities ({rows} entity rows), CPU s (median):")
    print(f"  DuckDB, one Arrow table per insert (ours):  {arrow:.3f}")
    print(f"  DuckDB, executemany (row by row):           {row_by_row:.3f}")
    if args.postgres:
        with scratch_database(args.postgres) as url:
            print(f"  Postgres, executemany (ours):               {flush_cpu(url, args):.3f}")


@contextlib.contextmanager
def scratch_database(admin_url: str) -> Iterator[str]:
    """A database of its own on that server, dropped afterwards (the one named is left untouched)."""
    name = f"fleet_bench_flush_{os.getpid()}"
    admin = sa.create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
    try:
        yield str(sa.make_url(admin_url).set(database=name).render_as_string(hide_password=False))
    finally:
        with admin.connect() as conn:
            conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


def _executemany_on_duckdb(url: str, args: argparse.Namespace) -> float:
    original = queries.insert_rows

    def executemany(session: sa.orm.Session, model: type[Base], rows: list[dict[str, object]]) -> None:
        if rows:
            session.execute(sa.insert(model), rows)

    queries.insert_rows = executemany  # type: ignore[assignment]
    try:
        return flush_cpu(url, args)
    finally:
        queries.insert_rows = original  # type: ignore[assignment]


if __name__ == "__main__":
    main()
