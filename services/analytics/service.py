"""Analytics: SQL over the catalog and the telemetry tables, answers in JSON, CSV, Arrow or Parquet."""

from __future__ import annotations

import dataclasses
import decimal
import functools
import io
import json
import tempfile
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog import queries
from catalog.db import session_scope
from catalog.models import Run, RunObject
from catalog.sql_tables import SQL_CATALOG_TABLES, catalog_tables
from core.errors import InvalidArgumentError
from core.states import Tier
from services.analytics import sql
from services.analytics.extract import TABLES, extract_file
from services.analytics.pool import Prepared, SqlPool
from services.analytics.store import write_analytics
from services.ingest.service import IngestService
from services.lakehouse import scan as lakehouse_scan
from services.lakehouse.sync import copy_now
from services.node import Node, OnNode

FORMATS = {
    "json": "application/json",
    "csv": "text/csv",
    "arrow": "application/vnd.apache.arrow.stream",
    "parquet": "application/vnd.apache.parquet",
}


@dataclass
class Analytics(OnNode):
    """The node (its catalog, the warm store the tables are extracted to, its clock) and the SQL
    workers' limits."""

    node: Node
    limits: sql.Limits
    _pool: SqlPool | None = field(default=None, init=False, repr=False)
    _pool_lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False)

    def s3_access(self) -> sql.S3Access | None:
        access = getattr(self.warm, "access", None)
        if access is None:
            return None
        found = access()
        if not found["key_id"]:
            return None
        return sql.S3Access(
            found["key_id"],
            found["secret"],
            found["region"],
            found["endpoint"],
            found["use_ssl"],
            found["session_token"],
        )

    @property
    def root(self) -> str:
        """Where the tables' files are: the lakehouse's folder, or the per-run files' without one."""
        lake = self.node.lakehouse
        return lakehouse_scan.root(lake) if lake is not None else sql.analytics_root(self.warm.url)

    @property
    def pool(self) -> SqlPool:
        """The SQL workers, started with the first query (or by `start`)."""
        with self._pool_lock:
            if self._pool is None:
                plan = functools.partial(read_ahead, self)
                self._pool = SqlPool(self.limits, httpfs=self.root.startswith("s3://"), read_ahead=plan)
            return self._pool

    def start(self) -> None:
        """Start the idle SQL workers now, so the first query does not wait for them."""
        self.pool.start()

    def close(self) -> None:
        with self._pool_lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.close()


def analytics_files(session: Session, root: str, tables: Iterable[str]) -> dict[str, list[str]]:
    """Each analytics table's files, as the catalog lists them: one set per run that is not deleted
    (files the store holds but the catalog does not, such as a crash's leftovers, are not read)."""
    wanted = {f"analytics/{t}": t for t in tables}
    files: dict[str, list[str]] = {t: [] for t in wanted.values()}
    if not wanted:
        return files
    rows = session.execute(
        sa.select(RunObject.name, RunObject.key)
        .join(Run, Run.id == RunObject.run_id)
        .where(RunObject.name.in_(list(wanted)), Run.tier != Tier.DELETED)
        .order_by(RunObject.key)
    ).all()
    for name, key in rows:
        table = wanted[name]
        if key.startswith(f"{name}/") and ".." not in key.split("/"):  # the catalog's keys, kept in the table
            files[table].append(f"{root}/{key.removeprefix('analytics/')}")
    return files


def prepare(ctx: Analytics, named: set[str]) -> Prepared:
    """The catalog rows and analytics file lists of the views a query names (only those: a snapshot
    copies a whole table, and binding an analytics view reads the footer of each of its files)."""
    tables = [t for t in TABLES if t in named]
    lake = ctx.node.lakehouse
    with session_scope(ctx.catalog) as session:
        per_run = analytics_files(session, ctx.root, tables) if lake is None else {}
        rows = catalog_tables(session, [t for t in SQL_CATALOG_TABLES if t in named])
    if lake is None:  # each run's file, read as one group whatever its columns
        files = {t: [paths] if paths else [] for t, paths in per_run.items()}
    else:  # the Iceberg tables' data files as of their current snapshots, grouped by their columns
        files = {table: lakehouse_scan.data_files(lake, table) for table in tables}
    return Prepared(files, rows)


def read_ahead(ctx: Analytics, tables: tuple[str, ...]) -> dict[str, Any] | None:
    """What an idle worker reads ahead for the next query (`warming.py`): the current data files of
    these lakehouse tables, up to `read_ahead_files` of them. Nothing without the lakehouse: a run's
    per-run file is rewritten in place, so a footer read ahead could be stale by the query."""
    lake = ctx.node.lakehouse
    if lake is None or ctx.limits.read_ahead_files <= 0:
        return None
    files: list[str] = []
    for table in tables:
        files += [path for group in lakehouse_scan.data_files(lake, table) for path in group]
    if not files:
        return None
    s3 = ctx.s3_access()
    access = dataclasses.asdict(s3) if s3 else None
    return {"root": ctx.root, "s3": access, "files": files[: ctx.limits.read_ahead_files]}


def request(ctx: Analytics, text: str) -> dict[str, Any]:
    """What a worker is told: the query, where the files are, the S3 access, and the server's own
    strings it must keep out of answers and errors."""
    s3 = ctx.s3_access()
    root = ctx.root
    hidden = [root, root.rsplit("/", 1)[0], ctx.warm.url, ctx.pool.workdir, str(Path.home())]
    if s3 is not None:
        hidden += [s3.key_id, s3.secret, s3.session_token or "", s3.endpoint or ""]
    layout = sql.ICEBERG if ctx.node.lakehouse is not None else sql.PER_RUN
    s3_access = dataclasses.asdict(s3) if s3 else None
    return {"query": text, "root": root, "layout": layout, "s3": s3_access, "hidden": hidden}


async def query(ctx: Analytics, text: str) -> pa.Table:
    """The answer, computed in a worker process; this coroutine holds no thread while it waits."""
    return await ctx.pool.run(request(ctx, text), functools.partial(prepare, ctx))


def pick_format(name: str | None, accept: str | None) -> str:
    """`?format=` wins, else the Accept header, else JSON."""
    if name:
        if name not in FORMATS:
            raise InvalidArgumentError(f"format {name!r} is not one of {', '.join(FORMATS)}")
        return name
    for part in (accept or "").split(","):
        media = part.split(";")[0].strip()
        for fmt, known in FORMATS.items():
            if media == known:
                return fmt
    return "json"


def encode(table: pa.Table, fmt: str) -> bytes:
    if fmt == "arrow":
        sink = io.BytesIO()
        with pa.ipc.new_stream(sink, table.schema) as writer:
            writer.write_table(table)
        return sink.getvalue()
    if fmt == "parquet":
        sink = io.BytesIO()
        pq.write_table(table, sink)
        return sink.getvalue()
    if fmt == "csv":
        sink = io.BytesIO()
        pacsv.write_csv(_flat(textual(table)), sink)
        return sink.getvalue()
    plain = textual(table)
    body = {
        "columns": [{"name": f.name, "type": str(t.type)} for f, t in zip(plain.schema, table.schema, strict=True)],
        "rows": [list(r.values()) for r in plain.to_pylist()],
        "row_count": table.num_rows,
    }
    return json.dumps(body, default=_json_value).encode()


def _json_value(value: Any) -> Any:
    if isinstance(value, decimal.Decimal):  # DuckDB's HUGEINT (sum of integers) and DECIMAL: numbers
        return int(value) if value == value.to_integral_value() else float(value)
    return str(value)


def _flat(table: pa.Table) -> pa.Table:
    """Lists, structs and maps as JSON text: CSV has no nested values."""
    columns = [
        pa.array([None if v is None else json.dumps(v, default=_json_value) for v in c.to_pylist()], pa.string())
        if pa.types.is_nested(c.type)
        else c
        for c in table.columns
    ]
    return pa.table(columns, names=table.column_names)


def textual(table: pa.Table) -> pa.Table:
    """Timestamps and durations as text or integers, so JSON and CSV keep nanoseconds."""
    columns = []
    for column in table.columns:
        if pa.types.is_timestamp(column.type) or pa.types.is_date(column.type):
            column = column.cast(pa.string())
        elif pa.types.is_duration(column.type):
            column = column.cast(pa.int64())
        columns.append(column)
    return pa.table(columns, names=table.column_names)


def extract_hot_run(ctx: Analytics, ingest: IngestService, run_id: str) -> list[dict[str, Any]]:
    """Write a hot run's analytics tables now (promotion rewrites them when the run is sealed)."""
    run = ingest.hot_run(run_id)
    if run is None:
        raise queries.run_not_found(run_id)
    record = run.record(ctx.node.default_robot)
    with tempfile.TemporaryDirectory(prefix="fleet-analytics-") as spill:
        files = extract_file(run_id, run.path, run.size, Path(spill)).files()
        objects = write_analytics(ctx.warm, files, run_id, record.robot_id, record.date.isoformat())
    with session_scope(ctx.catalog, write=True) as session:  # the catalog lists each run's one copy
        stale = queries.replace_analytics(session, run_id, objects)
    for key in stale:  # written before under another robot or date
        ctx.warm.delete(key)
    copy_now(ctx.node.lakehouse, ctx.catalog, ctx.warm, ctx.clock, [run_id])
    return [{"table": o.name.removeprefix("analytics/"), "key": o.key, "bytes": o.size} for o in objects]
