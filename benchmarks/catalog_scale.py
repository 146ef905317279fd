"""Benchmark: the catalog's queries at fleet scale, a million runs on Postgres (100,000 on DuckDB).

    .venv/bin/python benchmarks/catalog_scale.py [--catalog postgres|duckdb] [--runs N] [--entities 8]
        [--repeat 20] [--scan-repeat 3] [--postgres URL] [--keep | --reuse NAME] [--json]

1. A catalog of its own: on Postgres a database `fleet_scale_PID` made through `--postgres` (default
   the local server, through its `postgres` database; no other database is touched), on DuckDB a
   file in a temporary folder (`--reuse PATH` to keep one). Migrated to head by the project's runner
   (`catalog.db.upgrade`, timed: on a reused catalog that is the new revisions on a full catalog),
   then filled (`benchmarks/catalog_scale_fill.py`: `--runs` runs of 200 robots over a year with
   everything a run has, 24 rows per run in all at `--entities 8`) in bulk, timed; vacuumed and
   analyzed. `--keep` keeps the catalog afterwards and prints its name; `--reuse NAME` measures a
   kept one again without filling it.
2. Each query through the code that answers it, on sessions of an engine made as `fleet serve`
   makes it: `GET /v1/runs` (`services.runs.service.runs_answer`) with no filter, each filter and
   each sort, the second page by cursor; a run's page (`run_answer`, a different run each time);
   `fleet runs ls --robot R` (the REST app in-process, as the CLI asks, auth off); the segment table
   of the `inspection` dataset (`services.redap.segments.scan`: the first part, and the whole scan
   `--scan-repeat` times); the console's overview (`services.runs.fleet.overview`, after the
   fleet totals job has counted once, as a running depot's has) and that job's count
   (`services.runs.totals.count`, once a minute); the retention plan
   (`services.retention.service.plan_answer`, every action).
3. Per query: one call to warm up, whose SQL is captured (a `before_cursor_execute` listener), then
   `--repeat` calls timed: p50 and p95 in ms. "SQL" is the database alone for the statements of
   one call: on Postgres the sum of their `EXPLAIN (ANALYZE, BUFFERS)` planning and execution times,
   on DuckDB the median of 3 runs of them through the driver; the rest of a call is Python (the
   ORM, JSON, Arrow). For a query whose p95 is over 100 ms, the plans of its two slowest statements
   are printed (Postgres).
4. On Postgres, the catalog's size: `pg_database_size`, and rows and bytes (table, indexes) per table.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import sqlalchemy as sa  # noqa: E402
from sqlalchemy.orm import sessionmaker  # noqa: E402

from benchmarks.catalog_scale_fill import Fleet  # noqa: E402
from benchmarks.catalog_scale_load import fill, finish  # noqa: E402
from benchmarks.catalog_scale_queries import Query, Scene, queries  # noqa: E402
from catalog.db import create_engine, upgrade  # noqa: E402

SLOW_MS = 100.0
LONG_S = 2.0  # a query whose first call takes longer is timed --scan-repeat times only
TIMEOUT_S = 120.0  # a statement timeout far above FLEET_CATALOG_TIMEOUT_S (10 s), so a slow query is measured
DEFAULT_RUNS = {"postgres": 1_000_000, "duckdb": 100_000}
ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"


@dataclass
class Captured:
    """The statements the catalog was sent while `on`."""

    on: bool = False
    statements: list[tuple[str, Any]] = field(default_factory=list)

    def listen(self, engine: sa.Engine) -> None:
        def before(conn: Any, cursor: Any, statement: str, parameters: Any, context: Any, many: bool) -> None:
            if self.on and not many:
                self.statements.append((statement, parameters))

        sa.event.listen(engine, "before_cursor_execute", before)

    @contextlib.contextmanager
    def capturing(self) -> Iterator[list[tuple[str, Any]]]:
        self.statements, self.on = [], True
        try:
            yield self.statements
        finally:
            self.on = False


@dataclass
class Measured:
    name: str
    times_ms: list[float]
    statements: int
    sql_ms: float
    plans: list[tuple[float, str]]  # (execution ms, EXPLAIN text) of the slowest statements

    def percentile(self, q: float) -> float:
        ordered = sorted(self.times_ms)
        return ordered[min(len(ordered) - 1, max(0, round(q * (len(ordered) - 1))))]

    def to_dict(self) -> dict[str, Any]:
        return {
            "query": self.name,
            "p50_ms": round(self.percentile(0.5), 2),
            "p95_ms": round(self.percentile(0.95), 2),
            "sql_ms": round(self.sql_ms, 2),
            "statements": self.statements,
            "calls": len(self.times_ms),
        }


def explain_postgres(engine: sa.Engine, statement: str, parameters: Any) -> tuple[float, str]:
    """(planning + execution ms, the plan) of one statement, run by EXPLAIN (ANALYZE, BUFFERS)."""
    raw: Any = engine.raw_connection()
    try:
        with raw.cursor() as cursor:
            cursor.execute("EXPLAIN (ANALYZE, BUFFERS) " + statement, parameters or None)
            lines = [row[0] for row in cursor.fetchall()]
        raw.rollback()
    finally:
        raw.close()
    took = sum(
        float(line.split(":")[1].split()[0]) for line in lines if line.startswith(("Planning Time", "Execution Time"))
    )
    return took, "\n".join(lines)


def time_duckdb(engine: sa.Engine, statement: str, parameters: Any) -> tuple[float, str]:
    """The median ms of 3 runs of one statement through DuckDB's driver, all rows fetched."""
    raw: Any = engine.raw_connection()
    try:
        times = []
        for _ in range(3):
            started = time.perf_counter()
            raw.driver_connection.execute(statement, parameters or None).fetchall()
            times.append((time.perf_counter() - started) * 1000)
    finally:
        raw.close()
    return statistics.median(times), ""


def measure(engine: sa.Engine, captured: Captured, query: Query, repeat: int, few: int) -> Measured:
    """`repeat` timed calls after the warm-up, or `few` when the warm-up took over LONG_S."""
    with captured.capturing() as statements:
        started = time.perf_counter()
        query.call(0)
        if time.perf_counter() - started > LONG_S:
            repeat = min(repeat, few)
    times = []
    for n in range(1, repeat + 1):
        started = time.perf_counter()
        query.call(n)
        times.append((time.perf_counter() - started) * 1000)
    explain = time_duckdb if engine.dialect.name == "duckdb" else explain_postgres
    timed = [explain(engine, statement, parameters) for statement, parameters in statements]
    slowest = sorted(timed, key=lambda t: -t[0])[:2]
    return Measured(query.name, times, len(statements), sum(t[0] for t in timed), slowest)


def print_table(results: list[Measured]) -> None:
    print(f"\n{'query':<52} {'p50 ms':>9} {'p95 ms':>9} {'SQL ms':>9} {'stmts':>6} {'calls':>6}")
    for r in results:
        flag = "  SLOW" if r.percentile(0.95) > SLOW_MS else ""
        p50, p95 = r.percentile(0.5), r.percentile(0.95)
        print(f"{r.name:<52} {p50:>9.1f} {p95:>9.1f} {r.sql_ms:>9.1f} {r.statements:>6} {len(r.times_ms):>6}{flag}")


def print_plans(results: list[Measured]) -> None:
    for r in results:
        if r.percentile(0.95) <= SLOW_MS or not any(plan for _, plan in r.plans):
            continue
        print(f"\n--- {r.name}: p95 {r.percentile(0.95):.1f} ms; its slowest statements' plans")
        for took, plan in r.plans:
            print(f"({took:.1f} ms)\n{plan}\n")


# --- the catalog: made, reused, sized, dropped ----------------------------------------------------


@contextlib.contextmanager
def catalog_url(args: argparse.Namespace) -> Iterator[tuple[str, bool]]:
    """(the catalog's URL, whether it was made now and needs filling)."""
    if args.catalog == "duckdb":
        if args.reuse:
            yield f"duckdb:///{args.reuse}", not Path(args.reuse).exists()
            return
        folder = Path(tempfile.mkdtemp(prefix="fleet_scale_"))
        yield f"duckdb:///{folder / 'catalog.duckdb'}", True
        if args.keep:
            print(f"kept: --reuse {folder / 'catalog.duckdb'}")
        return
    admin = sa.create_engine(args.postgres, isolation_level="AUTOCOMMIT")
    name = args.reuse or f"fleet_scale_{os.getpid()}"
    url = sa.make_url(args.postgres).set(database=name).render_as_string(hide_password=False)
    with admin.connect() as conn:
        fresh = conn.execute(sa.text("SELECT 1 FROM pg_database WHERE datname = :n"), {"n": name}).first() is None
        if fresh:
            conn.execute(sa.text(f'CREATE DATABASE "{name}"'))
    try:
        yield url, fresh
    finally:
        if args.keep or args.reuse:
            print(f'kept: --reuse {name}  (drop it with: DROP DATABASE "{name}")')
        else:
            with admin.connect() as conn:
                conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


def postgres_sizes(engine: sa.Engine) -> dict[str, Any]:
    """The database's size, and each table's rows, heap bytes and index bytes."""
    with engine.connect() as conn:
        total = conn.execute(sa.text("SELECT pg_database_size(current_database())")).scalar_one()
        rows = conn.execute(
            sa.text(
                "SELECT c.relname, c.reltuples::bigint, pg_table_size(c.oid), pg_indexes_size(c.oid) "
                "FROM pg_class c JOIN pg_namespace n ON n.oid = c.relnamespace "
                "WHERE n.nspname = 'public' AND c.relkind = 'r' ORDER BY pg_total_relation_size(c.oid) DESC"
            )
        ).all()
        indexes = conn.execute(
            sa.text(
                "SELECT indexrelid::regclass::text, pg_relation_size(indexrelid) FROM pg_index i "
                "JOIN pg_class c ON c.oid = i.indrelid JOIN pg_namespace n ON n.oid = c.relnamespace "
                "WHERE n.nspname = 'public' ORDER BY 2 DESC"
            )
        ).all()
    return {
        "database_bytes": int(total),
        "tables": [{"table": t, "rows": int(r), "table_bytes": int(s), "index_bytes": int(i)} for t, r, s, i in rows],
        "indexes": [{"index": name, "bytes": int(size)} for name, size in indexes],
    }


def print_sizes(sizes: dict[str, Any]) -> None:
    print(f"\ndatabase: {sizes['database_bytes'] / 2**30:.2f} GiB")
    print(f"{'table':<22} {'rows':>12} {'table MiB':>10} {'index MiB':>10}")
    for t in sizes["tables"]:
        if t["rows"] > 0:
            print(
                f"{t['table']:<22} {t['rows']:>12,} {t['table_bytes'] / 2**20:>10.1f} {t['index_bytes'] / 2**20:>10.1f}"
            )
    print("\nindexes over 1 MiB:")
    for i in sizes["indexes"]:
        if i["bytes"] > 2**20:
            print(f"  {i['index']:<48} {i['bytes'] / 2**20:>8.1f} MiB")


def prepare(url: str, fresh: bool, args: argparse.Namespace, now: dt.datetime) -> tuple[sa.Engine, dict[str, Any]]:
    """The catalog migrated (and filled when new); what that took."""
    engine = create_engine(url, TIMEOUT_S) if url.startswith("postgresql") else create_engine(url)
    took: dict[str, Any] = {}
    started = time.perf_counter()
    before, after = upgrade(engine)
    took["migrate_s"], took["migrated"] = round(time.perf_counter() - started, 1), f"{before} -> {after}"
    print(f"migrated {before} -> {after} in {took['migrate_s']} s")
    if fresh:
        started = time.perf_counter()
        per_table = fill(engine, Fleet(args.runs, args.entities, now), lambda line: print(line, flush=True))
        took["fill_s"] = round(time.perf_counter() - started, 1)
        took["fill_tables_s"] = {name: round(s, 1) for name, s in per_table.items()}
        print(f"filled in {took['fill_s']} s: " + ", ".join(f"{k} {v}" for k, v in took["fill_tables_s"].items()))
    took["finish_s"] = round(finish(engine, print), 1)
    return engine, took


def fleet_now(engine: sa.Engine) -> dt.datetime:
    """The fill's "now" (kept in the catalog: the newest run's last data), so a reused catalog is
    measured as of the moment it was filled."""
    with engine.connect() as conn:
        found = conn.execute(sa.text("SELECT max(updated_at) FROM runs")).scalar_one()
    moment = found if isinstance(found, dt.datetime) else dt.datetime.now(dt.UTC)
    return (moment if moment.tzinfo else moment.replace(tzinfo=dt.UTC)).replace(microsecond=0) + dt.timedelta(seconds=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--catalog", choices=("postgres", "duckdb"), default="postgres")
    parser.add_argument("--runs", type=int, help="runs to fill (default 1,000,000 on Postgres, 100,000 on DuckDB)")
    parser.add_argument("--entities", type=int, default=8, help="entities per run (default 8)")
    parser.add_argument("--repeat", type=int, default=20, help="timed calls per query (default 20)")
    parser.add_argument(
        "--scan-repeat", type=int, default=3, help=f"timed calls of the whole scan and of queries over {LONG_S:g} s (3)"
    )
    parser.add_argument("--postgres", default=os.environ.get("FLEET_SCALE_PG_URL", ADMIN_URL), help="server to use")
    parser.add_argument("--keep", action="store_true", help="keep the catalog afterwards")
    parser.add_argument("--reuse", help="a kept catalog (database name, or DuckDB file) to measure again")
    parser.add_argument("--only", action="append", help="measure only queries whose name contains this (repeatable)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON too")
    args = parser.parse_args()
    args.runs = args.runs or DEFAULT_RUNS[args.catalog]
    with catalog_url(args) as (url, fresh):
        engine, took = prepare(url, fresh, args, dt.datetime.now(dt.UTC).replace(microsecond=0))
        captured = Captured()
        captured.listen(engine)
        with Scene.open(sessionmaker(engine), fleet_now(engine)) as scene:
            results = [
                measure(engine, captured, q, args.scan_repeat if q.whole_scan else args.repeat, args.scan_repeat)
                for q in queries(scene)
                if not args.only or any(part in q.name for part in args.only)
            ]
        print_table(results)
        print_plans(results)
        sizes = postgres_sizes(engine) if engine.dialect.name == "postgresql" else None
        if sizes is not None:
            print_sizes(sizes)
        engine.dispose()
    if args.json:
        print(
            json.dumps(
                {
                    "catalog": args.catalog,
                    "runs": args.runs,
                    **took,
                    "queries": [r.to_dict() for r in results],
                    "sizes": sizes,
                },
                indent=1,
            )
        )


if __name__ == "__main__":
    main()
