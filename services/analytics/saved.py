"""Queries for people: a query's answer as the console shows it (its first rows, and the chart a
two-column answer makes), and saved queries (drawn on the dashboards, computed at every look so
they follow the runs sealed since). The SQL runs in the same sandboxed workers as `POST /v1/sql`."""

from __future__ import annotations

import datetime as dt
import decimal
import functools
import math
import secrets
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import pyarrow as pa

from catalog import saved_queries
from catalog.db import session_scope
from catalog.saved_queries import CHARTS, SavedQueryRecord
from catalog.sql_tables import CATALOG_TABLES, CORPUS_TABLES
from core.errors import FleetError, InvalidArgumentError
from services.analytics import service
from services.analytics.extract import FIXED_COLUMNS, LOG_TIME, PARTITION_COLUMNS
from services.analytics.service import Analytics

MAX_SHOWN = 1_000  # rows of an answer shown on a page (the download has them all)
MAX_POINTS = 1_000  # points of a line chart
MAX_BARS = 100  # bars of a bar chart
NAME_LENGTH = 256

# The dashboards' first example: volts each robot's battery lost per day (each run's first minus
# its last reading, summed over the robot's runs of that day). Two columns: a label and a number.
EXAMPLE = """\
-- Battery drain per robot per day: volts lost in each run, summed by robot and day
WITH per_run AS (
  SELECT robot_id, date, run_id, max(value) - min(value) AS drain
  FROM scalars
  WHERE entity = '/battery/voltage'
  GROUP BY robot_id, date, run_id
)
SELECT robot_id || ' ' || CAST(date AS VARCHAR) AS robot_day, sum(drain) AS drain_volts
FROM per_run
GROUP BY robot_id, date
ORDER BY robot_day"""


@dataclass(frozen=True)
class TableGuide:
    """A table queries may read, with its columns (name, type), for people writing queries."""

    name: str
    kind: str  # catalog | analytics
    columns: tuple[tuple[str, str], ...]
    note: str = ""


def tables() -> list[TableGuide]:
    """The tables the SQL sees: the catalog's (as in the catalog) and the analytics tables (their
    fixed columns, log_time, one column per other timeline of the run, and the partition)."""
    guides = [
        TableGuide(name, "catalog", tuple((c.name, _sql_type(c.type)) for c in model.__table__.columns))
        for name, model in CATALOG_TABLES.items()
    ]
    guides += [
        TableGuide(name, "catalog", tuple((label, _sql_type(c.type)) for label, c in columns))
        for name, columns in CORPUS_TABLES.items()
    ]
    types = {"instance": "INTEGER", "value": "DOUBLE", "tx": "DOUBLE", "ty": "DOUBLE", "tz": "DOUBLE"}
    types.update({q: "DOUBLE" for q in ("qx", "qy", "qz", "qw")})
    for name, fixed in FIXED_COLUMNS.items():
        columns = [(c, types.get(c, "VARCHAR")) for c in fixed]
        columns += [(LOG_TIME, "TIMESTAMP_NS"), (PARTITION_COLUMNS[0], "VARCHAR"), (PARTITION_COLUMNS[1], "DATE")]
        guides.append(
            TableGuide(name, "analytics", tuple(columns), "plus one column per other timeline of the run (frame, ...)")
        )
    return guides


def _sql_type(column_type: Any) -> str:
    name = type(column_type).__name__.upper()
    return {"STRING": "VARCHAR", "TEXT": "VARCHAR", "BIGINTEGER": "BIGINT", "DATETIME": "TIMESTAMPTZ"}.get(name, name)


def run_sql(ctx: Analytics, text: str) -> pa.Table:
    """The answer to `text`, computed in a SQL worker; the calling thread waits for it (the pool
    admits a bounded number of queries, so at most that many threads wait)."""
    if not text.strip():
        raise InvalidArgumentError("the query is empty: write one SELECT over the tables listed beside the box")
    future = ctx.pool.submit(service.request(ctx, text), functools.partial(service.prepare, ctx))
    return future.result()


# --- an answer as a page shows it ---------------------------------------------------------------


@dataclass(frozen=True)
class Chart:
    """A two-column answer drawn: `xs` (numbers, or ns since the epoch for times) or `labels`
    (text) against `ys`. `kind` is line (x numbers or times) or bar (x text)."""

    kind: str  # line | bar
    x_name: str
    y_name: str
    x_format: str  # number | time_ns | text
    xs: tuple[float, ...] = ()
    labels: tuple[str, ...] = ()
    ys: tuple[float, ...] = ()
    dropped: int = 0  # points beyond what a chart draws

    @property
    def points(self) -> list[tuple[float, float]]:
        return list(zip(self.xs, self.ys, strict=True))

    def as_kind(self, wanted: str) -> Chart:
        """This chart drawn as `wanted` (line or bar) where it can be: bars of numbers or times
        label them; a line over text labels stays bars."""
        if wanted == self.kind or wanted == "line":
            return self
        labels = tuple(_x_text(x, self.x_format) for x in self.xs)
        kept = min(len(labels), MAX_BARS)
        return Chart(
            "bar",
            self.x_name,
            self.y_name,
            "text",
            labels=labels[:kept],
            ys=self.ys[:kept],
            dropped=self.dropped + len(labels) - kept,
        )


@dataclass(frozen=True)
class Answer:
    """The first `MAX_SHOWN` rows of an answer as text, its size, and its chart if it makes one."""

    columns: tuple[str, ...]
    types: tuple[str, ...]
    numeric: tuple[bool, ...]
    rows: list[list[str]] = field(default_factory=list)
    total: int = 0
    chart: Chart | None = None

    @property
    def truncated(self) -> bool:
        return self.total > len(self.rows)


def answer(table: pa.Table, shown: int = MAX_SHOWN) -> Answer:
    head = service.textual(table.slice(0, shown))
    rows = [[_cell(v) for v in row.values()] for row in head.to_pylist()] if head.num_columns else []
    return Answer(
        tuple(table.column_names),
        tuple(str(f.type) for f in table.schema),
        tuple(_is_number(f.type) for f in table.schema),
        rows,
        table.num_rows,
        chart_of(table),
    )


def _cell(value: Any) -> str:
    if value is None:
        return "NULL"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    if isinstance(value, decimal.Decimal):
        return str(int(value)) if value == value.to_integral_value() else str(value)
    if isinstance(value, bytes):
        return value.hex()
    return str(value)


def _is_number(kind: pa.DataType) -> bool:
    return bool(pa.types.is_integer(kind) or pa.types.is_floating(kind) or pa.types.is_decimal(kind))


def chart_of(table: pa.Table) -> Chart | None:
    """The chart of a two-column answer whose second column is numeric: a line if the first is a
    number or a time (sorted by it), bars if it is text; None for any other answer."""
    if table.num_columns != 2 or not _is_number(table.schema.field(1).type):
        return None
    x_type = table.schema.field(0).type
    x_name, y_name = table.column_names
    pairs = [
        (x, float(y))
        for x, y in zip(table.column(0).to_pylist(), table.column(1).to_pylist(), strict=True)
        if x is not None and y is not None and math.isfinite(float(y))
    ]
    if _is_number(x_type) or pa.types.is_timestamp(x_type) or pa.types.is_date(x_type):
        x_format = "number" if _is_number(x_type) else "time_ns"
        points = sorted((_x_number(x), y) for x, y in pairs)
        kept = points[:MAX_POINTS]
        return Chart(
            "line",
            x_name,
            y_name,
            x_format,
            xs=tuple(p[0] for p in kept),
            ys=tuple(p[1] for p in kept),
            dropped=len(points) - len(kept),
        )
    kept_pairs = pairs[:MAX_BARS]
    return Chart(
        "bar",
        x_name,
        y_name,
        "text",
        labels=tuple(_cell(x) for x, _ in kept_pairs),
        ys=tuple(y for _, y in kept_pairs),
        dropped=len(pairs) - len(kept_pairs),
    )


def _x_number(value: Any) -> float:
    if isinstance(value, dt.datetime):
        moment = value if value.tzinfo is not None else value.replace(tzinfo=dt.UTC)
        return (moment - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)) // dt.timedelta(microseconds=1) * 1000.0
    if isinstance(value, dt.date):
        return float((value - dt.date(1970, 1, 1)).days * 86_400 * 10**9)
    return float(value)


def _x_text(value: float, x_format: str) -> str:
    if x_format == "time_ns":
        return dt.datetime.fromtimestamp(value / 1e9, dt.UTC).strftime("%Y-%m-%d %H:%M:%S")
    return f"{value:g}"


# --- saved queries ---------------------------------------------------------------------------------


def save(ctx: Analytics, name: str, text: str, chart: str, created_by: str) -> SavedQueryRecord:
    """Save a query under a unique name, to be drawn as `chart` (line, bar or table)."""
    name = " ".join(name.split())
    if not name:
        raise InvalidArgumentError("a saved query needs a name: it is the chart's title on the dashboards")
    if len(name) > NAME_LENGTH:
        raise InvalidArgumentError(f"the name is {len(name)} characters long: at most {NAME_LENGTH}")
    if not text.strip():
        raise InvalidArgumentError("the query is empty: write one SELECT before saving it")
    if chart not in CHARTS:
        raise InvalidArgumentError(f"chart {chart!r} is not one of {', '.join(CHARTS)}")
    now = ctx.clock()
    record = SavedQueryRecord(f"q-{secrets.token_hex(6)}", name, text.strip(), chart, created_by, now, now)
    with session_scope(ctx.catalog, write=True) as session:
        return saved_queries.add_query(session, record)


def saved(ctx: Analytics) -> list[SavedQueryRecord]:
    """Every saved query, by name."""
    with session_scope(ctx.catalog) as session:
        return saved_queries.saved_queries(session)


def one(ctx: Analytics, query_id: str) -> SavedQueryRecord:
    """A saved query; NOT_FOUND if there is none with this id."""
    with session_scope(ctx.catalog) as session:
        found = saved_queries.saved_query(session, query_id)
    if found is None:
        raise saved_queries.query_not_found(query_id)
    return found


def delete(ctx: Analytics, query_id: str) -> SavedQueryRecord:
    with session_scope(ctx.catalog, write=True) as session:
        return saved_queries.delete_query(session, query_id)


@dataclass(frozen=True)
class Drawn:
    """A saved query's answer now, or why there is none (its query fails since a table changed,
    the workers are busy, the token's SQL rate is used up)."""

    query: SavedQueryRecord
    answer: Answer | None = None
    error: FleetError | None = None


def run_one(ctx: Analytics, query: SavedQueryRecord, admit: Callable[[], None] | None = None) -> Drawn:
    """A saved query's answer now. `admit` is called first (the caller's rate limit)."""
    try:
        if admit is not None:
            admit()
        return Drawn(query, answer(run_sql(ctx, query.sql), shown=100))
    except FleetError as exc:
        return Drawn(query, error=exc)


def run_all(
    ctx: Analytics, queries: Sequence[SavedQueryRecord], admit: Callable[[], None] | None = None
) -> list[Drawn]:
    """Every saved query's answer now: as many at once as the SQL pool runs, never more than it
    admits (a long dashboard does not take the queue from others)."""
    drawn: list[Drawn] = []
    at_once = max(1, ctx.limits.workers)
    for start in range(0, len(queries), at_once):
        batch = queries[start : start + at_once]
        pending: list[tuple[SavedQueryRecord, Any]] = []
        for query in batch:
            try:
                if admit is not None:
                    admit()
                pending.append((query, ctx.pool.submit(service.request(ctx, query.sql), _prepare(ctx))))
            except FleetError as exc:
                pending.append((query, exc))
        for query, waiting in pending:
            if isinstance(waiting, FleetError):
                drawn.append(Drawn(query, error=waiting))
                continue
            try:
                drawn.append(Drawn(query, answer(waiting.result(), shown=100)))
            except FleetError as exc:
                drawn.append(Drawn(query, error=exc))
    return drawn


def _prepare(ctx: Analytics) -> Callable[[set[str]], Any]:
    return functools.partial(service.prepare, ctx)
