"""Read-only SQL over the catalog and the analytics tables, in a sandboxed DuckDB.

This module runs inside a SQL worker process (services/analytics/worker.py), never in the server:
each query gets a fresh process and a fresh in-memory DuckDB. Before anything runs, the query's
syntax tree is checked against an allowlist: it may name only our views and its own CTEs, call only
harmless table functions, and no function that shows settings, variables or the environment. The
catalog tables are handed in as Arrow tables; the analytics tables are views over the explicit list
of their files the catalog holds (local or S3, through the httpfs extension loaded from its wheel:
nothing is downloaded). Then the sandbox closes: only those files are readable, no extension is
loaded, no setting changed. Answers and errors never carry the store's location.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import duckdb
import pyarrow as pa

from core.errors import (
    InvalidSqlError,
    QueryOutOfMemoryError,
    QueryTimeoutError,
    ResourceExhaustedError,
    ResultTooLargeError,
    SqlNotAllowedError,
    UnavailableError,
)
from services.storage.objectstore import StorageError


class SqlBusyError(ResourceExhaustedError):
    """The SQL workers and their queue are full, or a query waited its whole time limit for a worker:
    come back in a moment (most queries take seconds)."""

    def __init__(self, message: str, retry_after_s: int = 2) -> None:
        super().__init__(message)
        self.retry_after_s = max(1, retry_after_s)

    def headers(self) -> dict[str, str]:
        return {"Retry-After": str(self.retry_after_s)}


CATALOG_VIEWS = ("robots", "runs", "run_entities", "run_timelines", "run_metrics", "events", "run_tags")
ANALYTICS_VIEWS = ("scalars", "text_logs", "transforms")
VIEWS = CATALOG_VIEWS + ANALYTICS_VIEWS
TABLE_FUNCTIONS = frozenset({"range", "generate_series", "unnest", "json_each", "json_tree"})
# Scalar functions that read settings, variables, the environment or logs, or write logs.
DENIED_FUNCTIONS = frozenset(
    {
        "current_setting",
        "getenv",
        "getvariable",
        "write_log",
        "which_secret",
        "json_execute_serialized_sql",
        "query",
        "query_table",
    }
)
DENIED_PREFIXES = ("duckdb_", "pragma_")
SYSTEM_PREFIXES = ("duckdb_", "pragma_", "sqlite_", "pg_", "information_schema")
MEMORY_UNITS = {
    "b": 1,
    "kb": 10**3,
    "mb": 10**6,
    "gb": 10**9,
    "tb": 10**12,
    "kib": 2**10,
    "mib": 2**20,
    "gib": 2**30,
    "tib": 2**40,
}
LOG_TIME = "log_time"
PER_RUN, ICEBERG = "per-run", "iceberg"  # how the analytics tables' files are laid out
NEUTRAL_ROOT = "analytics"  # what answers and errors call the analytics folder


@dataclass(frozen=True)
class S3Access:
    """What DuckDB needs to read the analytics tables from S3."""

    key_id: str
    secret: str
    region: str
    endpoint: str | None = None  # host:port of an S3-compatible server
    use_ssl: bool = True
    session_token: str | None = None


@dataclass(frozen=True)
class Limits:
    rows: int = 100_000
    seconds: float = 30.0
    memory: str = "2GB"  # of the whole worker process (FLEET_SQL_MEMORY_LIMIT)
    threads: int = 4
    workers: int = 2  # queries running at once (FLEET_SQL_WORKERS)
    queue: int = 8  # queries waiting for a worker beyond those (FLEET_SQL_QUEUE)
    read_ahead_files: int = 1000  # footers an idle worker reads ahead (FLEET_SQL_READ_AHEAD_FILES)

    @property
    def memory_bytes(self) -> int:
        return memory_bytes(self.memory)


def memory_bytes(text: str) -> int:
    """`2GB`, `512MiB`, `1.5 GB` (DuckDB's notation: KB = 1000, KiB = 1024) in bytes."""
    found = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([kmgt]i?b|b)?\s*", text.lower())
    if not found:
        raise ValueError(f"memory limit {text!r} is not a size such as 2GB or 512MiB")
    return int(float(found[1]) * MEMORY_UNITS[found[2] or "b"])


def duckdb_memory(limits: Limits, baseline: int) -> int:
    """DuckDB's own memory_limit: most of what the process may use beyond the interpreter, so DuckDB
    spills or refuses before the server has to kill the worker."""
    return max(32 * 10**6, int((limits.memory_bytes - baseline) * 0.8))


_COLUMN_TYPES = {
    "run_id": "VARCHAR",
    "entity": "VARCHAR",
    "component": "VARCHAR",
    "instance": "INTEGER",
    "value": "DOUBLE",
    "level": "VARCHAR",
    "text": "VARCHAR",
}
_READ_ONLY = "queries are read-only, only SELECT (or EXPLAIN) statements over the catalog and analytics tables run here"
_WHAT_IS_ALLOWED = (
    f"queries read only the catalog views ({', '.join(CATALOG_VIEWS)}), the analytics tables "
    f"({', '.join(ANALYTICS_VIEWS)}), their own WITH tables and the table functions "
    f"{', '.join(sorted(TABLE_FUNCTIONS))}"
)


def httpfs_extension() -> str:
    """The httpfs extension shipped in the duckdb-extension-httpfs wheel for this DuckDB version."""
    import duckdb_extension_httpfs

    root = Path(duckdb_extension_httpfs.__file__).parent / "extensions"
    found = sorted(root.glob(f"v{duckdb.__version__}/httpfs.duckdb_extension"))
    if not found:
        raise UnavailableError(
            f"no httpfs extension for DuckDB {duckdb.__version__} in the "
            f"duckdb-extension-httpfs package: install "
            f"duckdb-extension-httpfs=={duckdb.__version__}"
        )
    return str(found[0])


def analytics_root(warm_url: str) -> str:
    """The analytics folder of the warm store as DuckDB names it (a path, or an s3:// URL)."""
    parsed = urlparse(warm_url)
    if parsed.scheme == "file":
        return str(Path(parsed.path) / "analytics")
    return warm_url.rstrip("/") + "/analytics"


# --- the allowlist ------------------------------------------------------------------------------


def check_query(con: duckdb.DuckDBPyConnection, query: str) -> set[str]:
    """Refuse anything but one read-only query over our views; returns the views it names."""
    try:
        statements = con.extract_statements(query)
    except duckdb.Error as exc:
        raise InvalidSqlError(f"the query does not parse: {first_line(exc)}") from None
    if len(statements) != 1:
        raise SqlNotAllowedError(f"one statement per query, got {len(statements)}: send them one at a time")
    kind = statements[0].type
    if kind == duckdb.StatementType.EXPLAIN:  # EXPLAIN ANALYZE runs the statement it explains: check it
        return check_query(con, _explained(statements[0].query))
    if kind != duckdb.StatementType.SELECT:
        name = str(kind).rsplit(".", 1)[-1].replace("_STATEMENT", "")
        name = "INSTALL or LOAD" if name == "LOAD" else name  # DuckDB files INSTALL under LOAD
        raise SqlNotAllowedError(f"{name} is not allowed: {_READ_ONLY}")
    serialized = con.execute("SELECT json_serialize_sql(?::VARCHAR)", [statements[0].query]).fetchone()
    tree = json.loads(serialized[0]) if serialized else {"error": True, "error_message": "no syntax tree"}
    if tree.get("error"):
        raise SqlNotAllowedError(
            f"this form of query is not supported here ({tree.get('error_message')}): "
            f"write it as a plain SELECT; {_WHAT_IS_ALLOWED}"
        )
    named: set[str] = set()
    for node, ctes in _walk(tree, frozenset()):
        _check_node(node, ctes, named)
    return named


def _walk(node: Any, ctes: frozenset[str]) -> Iterator[tuple[dict[str, Any], frozenset[str]]]:
    """Every object of the syntax tree, with the CTE names visible where it stands."""
    if isinstance(node, list):
        for item in node:
            yield from _walk(item, ctes)
        return
    if not isinstance(node, dict):
        return
    cte_map = node.get("cte_map")
    if isinstance(cte_map, dict):
        ctes = ctes | {str(entry["key"]).lower() for entry in cte_map.get("map", [])}
    yield node, ctes
    for value in node.values():
        yield from _walk(value, ctes)


def _check_node(node: dict[str, Any], ctes: frozenset[str], named: set[str]) -> None:
    kind = node.get("type")
    if kind == "BASE_TABLE":
        table = str(node.get("table_name", "")).lower()
        qualified = node.get("schema_name") not in ("", "main") or node.get("catalog_name") not in ("", "memory")
        if qualified or (table not in VIEWS and table not in ctes):
            if not qualified and re.fullmatch(r"[a-z_][a-z0-9_]*", table) and not table.startswith(SYSTEM_PREFIXES):
                raise InvalidSqlError(f"there is no table {table!r}: {_WHAT_IS_ALLOWED}")  # a typo, most likely
            raise SqlNotAllowedError(f"table {table!r} is not allowed: {_WHAT_IS_ALLOWED}")
        if table in VIEWS and table not in ctes:
            named.add(table)
    elif kind == "TABLE_FUNCTION":
        function = str(node.get("function", {}).get("function_name", "")).lower()
        if function not in TABLE_FUNCTIONS:
            raise SqlNotAllowedError(f"table function {function}() is not allowed: {_WHAT_IS_ALLOWED}")
    if "function_name" in node:
        function = str(node["function_name"]).lower()
        if function in DENIED_FUNCTIONS or function.startswith(DENIED_PREFIXES):
            raise SqlNotAllowedError(
                f"function {function}() is not allowed: it shows the server's settings or "
                "environment; every other scalar and aggregate function is"
            )


def _explained(query: str) -> str:
    """The statement an `EXPLAIN [ANALYZE] [(options)]` wraps."""
    starts = [pos for pos, _ in duckdb.tokenize(query)]
    i = 1  # past EXPLAIN
    if i < len(starts) and query[starts[i] : starts[i] + 7].upper() in ("ANALYZE", "ANALYSE"):
        i += 1
    depth = 0
    while i < len(starts) and (depth or query[starts[i]] == "("):
        depth += {"(": 1, ")": -1}.get(query[starts[i]], 0)
        i += 1
    return query[starts[i] :] if i < len(starts) else ""


def is_explain(con: duckdb.DuckDBPyConnection, query: str) -> bool:
    return bool(con.extract_statements(query)[0].type == duckdb.StatementType.EXPLAIN)


# --- the sandbox ----------------------------------------------------------------------------------


@contextmanager
def sandbox(
    con: duckdb.DuckDBPyConnection,
    root: str,
    catalog: dict[str, pa.Table],
    s3: S3Access | None,
    files: dict[str, list[list[str]]],
    layout: str = PER_RUN,
) -> Iterator[duckdb.DuckDBPyConnection]:
    """`con` with the given catalog tables and analytics views (`files`: table -> its files in
    groups, laid out as `layout` says), locked down: only those files are readable afterwards."""
    try:
        # the view is bound when created and again by the query: parse each footer (and HEAD each
        # file) once; the database lives for one query (and its worker's read-ahead of immutable
        # lakehouse files), so nothing cached can go stale
        cache_settings(con)
        if root.startswith("s3://") and any(files.values()):
            s3_secret(con, s3, root)
        for name, table in catalog.items():
            con.register(f"_catalog_{name}", table)
            con.execute(f"CREATE VIEW {name} AS SELECT * FROM _catalog_{name}")
        for table, groups in files.items():
            analytics_view(con, table, groups, layout)
        readable = sorted({p for groups in files.values() for group in groups for p in group})
        con.execute("SET allowed_directories = []")
        con.execute("SET allowed_paths = ?", [readable])
        con.execute("SET enable_external_access = false")
        con.execute("SET lock_configuration = true")
        yield con
    finally:
        con.close()


def cache_settings(con: duckdb.DuckDBPyConnection) -> None:
    """Keep parsed footers, and each file's size and time, for the database's life."""
    con.execute("SET parquet_metadata_cache = true")
    con.execute("SET enable_http_metadata_cache = true")


def analytics_view(con: duckdb.DuckDBPyConnection, table: str, groups: list[list[str]], layout: str = PER_RUN) -> None:
    """`table` over exactly these Parquet files; a table with no file is an empty view with the
    documented columns. PER_RUN: one group of a file per run under `robot_id=R/date=D/`, whose
    columns differ (binding the view reads every footer). ICEBERG: the lakehouse table's data files
    in groups with the same columns (binding reads one footer per group), which hold robot and date,
    and `log_time` to the microsecond beside its exact `log_time_ns` (the view's `log_time`)."""
    if any(groups):
        # Both layouts keep files under robot_id=R/date=D/ (Iceberg's identity partitions name their
        # folders so): a filter on robot or date skips the other folders' files unopened.
        options = "hive_partitioning = true, hive_types = {'robot_id': VARCHAR, 'date': DATE}"
        if layout == ICEBERG:
            parts = " UNION ALL BY NAME ".join(
                f"SELECT * FROM read_parquet([{listed(group)}], {options})" for group in groups if group
            )
            source = f"SELECT * REPLACE (make_timestamp_ns(log_time_ns) AS {LOG_TIME}) FROM ({parts})"
        else:
            paths = [p for group in groups for p in group]
            source = f"SELECT * FROM read_parquet([{listed(paths)}], union_by_name = true, {options})"
        try:
            con.execute(f"CREATE VIEW {table} AS {source}")
            return
        except duckdb.Error as exc:
            raise StorageError(f"cannot read the {table} table: {first_line(exc)}") from None
    from services.analytics.extract import FIXED_COLUMNS  # here: numpy is slow to import in a worker

    columns = ", ".join(f"NULL::{_COLUMN_TYPES.get(c, 'DOUBLE')} AS {c}" for c in FIXED_COLUMNS[table])
    con.execute(
        f"CREATE VIEW {table} AS SELECT {columns}, NULL::TIMESTAMP_NS AS {LOG_TIME}, "
        "NULL::VARCHAR AS robot_id, NULL::DATE AS date WHERE false"
    )


def listed(paths: list[str]) -> str:
    return ", ".join("'" + p.replace("'", "''") + "'" for p in paths)


def s3_secret(con: duckdb.DuckDBPyConnection, s3: S3Access | None, root: str) -> None:
    """The credentials as a secret scoped to the analytics folder: never as s3_* settings, which
    current_setting() would show (duckdb_secrets() shows a secret's scope, never its values)."""
    if s3 is None:
        raise UnavailableError("the analytics tables are on S3 but no S3 credentials were found: set AWS_* variables")
    con.execute(f"LOAD '{httpfs_extension()}'")
    options = {"KEY_ID": s3.key_id, "SECRET": s3.secret, "REGION": s3.region, "SCOPE": root.rstrip("/") + "/"}
    if s3.session_token:
        options["SESSION_TOKEN"] = s3.session_token
    parts = ["TYPE s3"] + [f"{k} '{v.replace(chr(39), chr(39) * 2)}'" for k, v in options.items()]
    if s3.endpoint:
        parts += [f"ENDPOINT '{s3.endpoint}'", "URL_STYLE 'path'", f"USE_SSL {str(s3.use_ssl).lower()}"]
    # OR REPLACE: an idle worker's read-ahead (warming.py) may have made the same one already
    con.execute(f"CREATE OR REPLACE SECRET fleet_s3 ({', '.join(parts)})")


def run(con: duckdb.DuckDBPyConnection, query: str, limits: Limits, max_bytes: int) -> pa.Table:
    """The query's answer, or the one error that says which limit or rule it broke (the time and
    memory limits are the server's to enforce: it stops the worker)."""
    try:
        con.execute(query)
        reader = con.to_arrow_reader(min(limits.rows + 1, 65_536))
        batches, rows, size = [], 0, 0
        for batch in reader:
            rows += batch.num_rows
            size += batch.nbytes
            if rows > limits.rows:
                raise ResultTooLargeError(
                    f"the answer has more than {limits.rows:,} rows (FLEET_SQL_MAX_ROWS): "
                    "aggregate, add a WHERE or a LIMIT"
                )
            if size > max_bytes:
                raise ResultTooLargeError(
                    f"the answer is larger than {limits.memory} (FLEET_SQL_MEMORY_LIMIT): "
                    "select fewer or shorter columns, aggregate, or add a LIMIT"
                )
            batches.append(batch)
        return pa.Table.from_batches(batches, schema=reader.schema)
    except duckdb.InterruptException:
        raise QueryTimeoutError(f"the query ran longer than {limits.seconds:g} s (FLEET_SQL_TIMEOUT_S)") from None
    except duckdb.OutOfMemoryException as exc:
        raise QueryOutOfMemoryError(out_of_memory(limits, first_line(exc))) from None
    except duckdb.PermissionException as exc:
        raise SqlNotAllowedError(f"not allowed: {first_line(exc)}; {_WHAT_IS_ALLOWED}") from None
    except duckdb.Error as exc:
        raise InvalidSqlError(first_line(exc)) from None


def out_of_memory(limits: Limits, detail: str = "") -> str:
    return (
        f"the query needs more memory than {limits.memory} (FLEET_SQL_MEMORY_LIMIT)"
        f"{': ' + detail if detail else ''}: filter by robot_id and date, aggregate, or select fewer columns"
    )


def first_line(exc: Exception) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


# --- nothing of the server's in answers or errors ------------------------------------------------


@dataclass(frozen=True)
class Scrubber:
    """Replaces the server's own strings (the analytics root, the worker's folder, the S3 endpoint and
    credentials) in text bound for a user."""

    hidden: tuple[str, ...]

    def text(self, value: str) -> str:
        value = re.sub(r"[^\s'\"()\[\],]*/(analytics|lakehouse)/", f"{NEUTRAL_ROOT}/", value)  # a file's path
        for secret in sorted((h for h in self.hidden if len(h.strip("/")) >= 3), key=len, reverse=True):
            neutral = secret.endswith(("/analytics", "/lakehouse"))
            value = value.replace(secret, NEUTRAL_ROOT if neutral else "[hidden]")
        return value

    def plan(self, value: str) -> str:
        """EXPLAIN text: the box renderer wraps file names over several lines, so the lines after a
        `Filename(s):` key are blanked in its box, then the rest is scrubbed as text."""
        lines = value.split("\n")
        for i, line in enumerate(lines):
            at = line.find("Filename(s):")
            if at < 0:
                continue
            left, right = line.rfind("│", 0, at), line.find("│", at)
            if left < 0 or right < 0:
                continue
            for j in range(i + 1, len(lines)):
                inner = lines[j][left + 1 : right]
                if not inner.strip():
                    break
                label = f"{NEUTRAL_ROOT}/..." if j == i + 1 else ""
                lines[j] = lines[j][: left + 1] + label.center(right - left - 1) + lines[j][right:]
        return self.text("\n".join(lines))

    def table(self, table: pa.Table) -> pa.Table:
        columns = [
            pa.array([None if v is None else self.plan(v) for v in c.to_pylist()], pa.string())
            if pa.types.is_string(c.type)
            else c
            for c in table.columns
        ]
        return pa.table(columns, names=table.column_names)
