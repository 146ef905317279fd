"""Benchmark: a catalog query with bound parameters on the embedded DuckDB catalog, without and
with `catalog.db.skip_missing_pandas` (DuckDB's driver tries `import pandas` for each bound
parameter; without pandas installed each try searches sys.path).

    .venv/bin/python benchmarks/duckdb_params.py [--queries 2000]

Each variant runs in a fresh process; prints the mean time per query.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

TIMED = """
import sys, time
sys.path.insert(0, {root!r})
import sqlalchemy as sa
from catalog.db import create_engine, skip_missing_pandas
import catalog.db
if not {shim}:
    catalog.db.skip_missing_pandas = lambda: None
engine = create_engine("duckdb:///{path}")
with engine.connect() as c:
    c.execute(sa.text("CREATE TABLE runs (id VARCHAR PRIMARY KEY, application_id VARCHAR)"))
    c.execute(sa.text("INSERT INTO runs SELECT 'run-' || i, 'app' FROM range(1000) t(i)"))
    c.commit()
    query = sa.text("SELECT count(*) FROM runs WHERE application_id = :app AND id <> :run")
    for _ in range(50):
        c.execute(query, {{"app": "app", "run": "x"}}).scalar()
    started = time.perf_counter()
    for _ in range({queries}):
        c.execute(query, {{"app": "app", "run": "x"}}).scalar()
    print((time.perf_counter() - started) / {queries} * 1000)
    ids = sa.select(sa.func.count()).select_from(sa.table("runs", sa.column("id")))
    many = ids.where(sa.column("id").in_([f"run-{{i}}" for i in range(1000)]))
    started = time.perf_counter()
    for _ in range(20):
        c.execute(many).scalar()
    print((time.perf_counter() - started) / 20 * 1000)
"""


def timed(shim: bool, queries: int) -> tuple[float, float]:
    """(ms per query with 2 parameters, ms per query with an IN list of 1,000)."""
    with tempfile.TemporaryDirectory() as folder:
        code = TIMED.format(root=str(ROOT), shim=shim, path=Path(folder) / "c.duckdb", queries=queries)
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        two, thousand = done.stdout.strip().splitlines()[-2:]
        return float(two), float(thousand)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--queries", type=int, default=2000)
    args = parser.parse_args()
    without, with_shim = timed(False, args.queries), timed(True, args.queries)
    for i, what in enumerate((f"2 bound parameters (mean of {args.queries})", "an IN list of 1,000 (mean of 20)")):
        print(f"a query with {what}:")
        print(f"  DuckDB's driver as is:      {without[i]:8.3f} ms")
        print(f"  with skip_missing_pandas:   {with_shim[i]:8.3f} ms  ({without[i] / with_shim[i]:.1f}x faster)")


if __name__ == "__main__":
    main()
