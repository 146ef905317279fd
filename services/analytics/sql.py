"""Read-only SQL over the catalog and the analytics tables, in a sandboxed DuckDB.

Each query gets a fresh in-memory DuckDB. The catalog tables are handed in as Arrow tables; the
analytics tables are views over their Parquet (local or S3, through the httpfs extension loaded
from its wheel: nothing is downloaded). Then the sandbox closes: no file or URL outside the
analytics data can be read, no extension loaded, no setting changed, and only one SELECT (or
EXPLAIN) statement is accepted. A row limit and a time limit bound every answer.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlparse

import duckdb
import pyarrow as pa

from services.analytics.extract import FIXED_COLUMNS, LOG_TIME, TABLES
from services.errors import ErrorCode, FleetError
from services.storage.objectstore import StorageError


class SqlNotAllowedError(FleetError):
    code = ErrorCode.SQL_NOT_ALLOWED


class InvalidSqlError(FleetError):
    code = ErrorCode.INVALID_SQL


class QueryTimeoutError(FleetError):
    code = ErrorCode.QUERY_TIMEOUT


class ResultTooLargeError(FleetError):
    code = ErrorCode.RESULT_TOO_LARGE


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
    memory: str = "2GB"
    threads: int = 4


_COLUMN_TYPES = {"run_id": "VARCHAR", "entity": "VARCHAR", "component": "VARCHAR", "instance": "INTEGER",
                 "value": "DOUBLE", "level": "VARCHAR", "text": "VARCHAR"}
_ALLOWED = {duckdb.StatementType.SELECT, duckdb.StatementType.EXPLAIN}


def httpfs_extension() -> str:
    """The httpfs extension shipped in the duckdb-extension-httpfs wheel for this DuckDB version."""
    import duckdb_extension_httpfs

    root = Path(duckdb_extension_httpfs.__file__).parent / "extensions"
    found = sorted(root.glob(f"v{duckdb.__version__}/httpfs.duckdb_extension"))
    if not found:
        raise FleetError(f"no httpfs extension for DuckDB {duckdb.__version__} in {root}: install "
                         f"duckdb-extension-httpfs=={duckdb.__version__}")
    return str(found[0])


def analytics_root(warm_url: str) -> str:
    """The analytics folder of the warm store as DuckDB names it (a path, or an s3:// URL)."""
    parsed = urlparse(warm_url)
    if parsed.scheme == "file":
        return str(Path(parsed.path) / "analytics")
    return warm_url.rstrip("/") + "/analytics"


def check_statement(con: duckdb.DuckDBPyConnection, query: str) -> None:
    try:
        statements = con.extract_statements(query)
    except duckdb.Error as exc:
        raise InvalidSqlError(f"the query does not parse: {exc}") from None
    if len(statements) != 1:
        raise SqlNotAllowedError(f"one statement per query, got {len(statements)}: send them one at a time")
    kind = statements[0].type
    if kind == duckdb.StatementType.EXPLAIN:  # EXPLAIN ANALYZE runs the statement it explains: check it too
        check_statement(con, _explained(statements[0].query))
        return
    if kind not in _ALLOWED:
        name = str(kind).rsplit(".", 1)[-1].replace("_STATEMENT", "")
        name = "INSTALL or LOAD" if name == "LOAD" else name  # DuckDB files INSTALL under LOAD
        raise SqlNotAllowedError(f"{name} is not allowed: queries are read-only, only SELECT (or EXPLAIN) "
                                 "statements over the catalog and analytics tables run here")


def _explained(query: str) -> str:
    """The statement an `EXPLAIN [ANALYZE] [(options)]` wraps."""
    starts = [pos for pos, _ in duckdb.tokenize(query)]
    i = 1  # past EXPLAIN
    if i < len(starts) and query[starts[i]:starts[i] + 7].upper() in ("ANALYZE", "ANALYSE"):
        i += 1
    depth = 0
    while i < len(starts) and (depth or query[starts[i]] == "("):
        depth += {"(": 1, ")": -1}.get(query[starts[i]], 0)
        i += 1
    return query[starts[i]:] if i < len(starts) else ""


@contextmanager
def sandbox(root: str, catalog: dict[str, pa.Table], limits: Limits, s3: S3Access | None,
            tables: Iterable[str] = TABLES) -> Iterator[duckdb.DuckDBPyConnection]:
    """A DuckDB with the given catalog tables and analytics views, locked down."""
    con = duckdb.connect(":memory:", config={"autoinstall_known_extensions": False,
                                             "autoload_known_extensions": False, "threads": limits.threads,
                                             "memory_limit": limits.memory})
    try:
        if root.startswith("s3://"):
            _s3(con, s3)
        for name, table in catalog.items():
            con.register(f"_catalog_{name}", table)
            con.execute(f"CREATE VIEW {name} AS SELECT * FROM _catalog_{name}")
        for table in tables:
            analytics_view(con, root, table)
        allowed = root.rstrip("/") + "/"
        con.execute("SET allowed_directories = [?]", [allowed])
        con.execute("SET enable_external_access = false")
        con.execute("SET lock_configuration = true")
        yield con
    finally:
        con.close()


def analytics_view(con: duckdb.DuckDBPyConnection, root: str, table: str) -> None:
    """`table` over its Parquet files (binding it reads each file's footer, for its columns); a table
    with no file yet is an empty view with the documented columns."""
    pattern = f"{root}/{table}/*/*/*.parquet".replace("'", "''")
    try:
        con.execute(f"CREATE VIEW {table} AS SELECT * FROM read_parquet('{pattern}', hive_partitioning = true, "
                    "union_by_name = true, hive_types = {'robot_id': VARCHAR, 'date': DATE})")
        return
    except duckdb.IOException as exc:
        if "No files found" not in str(exc):
            raise StorageError(f"cannot read the {table} table under {root}: {_first_line(exc)}") from None
    columns = ", ".join(f"NULL::{_COLUMN_TYPES.get(c, 'DOUBLE')} AS {c}" for c in FIXED_COLUMNS[table])
    con.execute(f"CREATE VIEW {table} AS SELECT {columns}, NULL::TIMESTAMP_NS AS {LOG_TIME}, "
                "NULL::VARCHAR AS robot_id, NULL::DATE AS date WHERE false")


def _s3(con: duckdb.DuckDBPyConnection, s3: S3Access | None) -> None:
    if s3 is None:
        raise FleetError("the analytics tables are on S3 but no S3 credentials were found: set AWS_* variables")
    con.execute(f"LOAD '{httpfs_extension()}'")
    options = {"TYPE": "s3", "KEY_ID": s3.key_id, "SECRET": s3.secret, "REGION": s3.region}
    if s3.session_token:
        options["SESSION_TOKEN"] = s3.session_token
    parts = [f"{k} '{v.replace(chr(39), chr(39) * 2)}'" if k != "TYPE" else f"{k} {v}" for k, v in options.items()]
    if s3.endpoint:
        parts += [f"ENDPOINT '{s3.endpoint}'", "URL_STYLE 'path'", f"USE_SSL {str(s3.use_ssl).lower()}"]
    con.execute(f"CREATE SECRET fleet_s3 ({', '.join(parts)})")


def run(con: duckdb.DuckDBPyConnection, query: str, limits: Limits) -> pa.Table:
    """The query's answer, or the one error that says which limit or rule it broke."""
    check_statement(con, query)
    timer = threading.Timer(limits.seconds, con.interrupt)
    timer.start()
    try:
        con.execute(query)
        reader = con.to_arrow_reader(min(limits.rows + 1, 65_536))
        batches, rows = [], 0
        for batch in reader:
            rows += batch.num_rows
            if rows > limits.rows:
                raise ResultTooLargeError(f"the answer has more than {limits.rows:,} rows (FLEET_SQL_MAX_ROWS): "
                                          "aggregate, add a WHERE or a LIMIT")
            batches.append(batch)
        return pa.Table.from_batches(batches, schema=reader.schema)
    except duckdb.InterruptException:
        raise QueryTimeoutError(f"the query ran longer than {limits.seconds:g} s (FLEET_SQL_TIMEOUT_S): "
                                "filter by robot_id and date to read fewer files, or aggregate less") from None
    except duckdb.PermissionException as exc:
        raise SqlNotAllowedError(f"not allowed: {_first_line(exc)}; queries read only the catalog views "
                                 "(robots, runs, run_entities, run_timelines) and the analytics tables "
                                 "(scalars, text_logs, transforms)") from None
    except duckdb.Error as exc:
        raise InvalidSqlError(_first_line(exc)) from None
    finally:
        timer.cancel()


def _first_line(exc: Exception) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
