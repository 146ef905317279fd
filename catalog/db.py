"""Catalog connections: one engine per URL, one session helper, and the schema-version checks.

The service never migrates silently: `fleet db upgrade` (or the embedded default on first start,
which says so) brings the schema to the head of `migrations/`; a catalog that is behind refuses
to start with one line naming the command.
"""

from __future__ import annotations

import importlib.util
import math
import re
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

import sqlalchemy as sa
from alembic.config import Config
from alembic.ddl.impl import DefaultImpl
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy.orm import Session, sessionmaker

from core.errors import ConflictError, UnavailableError

MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"


class DuckDBImpl(DefaultImpl):
    """Lets Alembic drive DuckDB (the embedded catalog) like any transactional SQL database."""

    __dialect__ = "duckdb"
    transactional_ddl = True


CONNECT_TIMEOUT_S = 5  # libpq's connect_timeout: a catalog host that does not answer fails this fast


def create_engine(url: str, timeout_s: float | None = None) -> sa.Engine:
    """An engine for `duckdb:///PATH` (embedded) or `postgresql+psycopg://...`."""
    if url.startswith("duckdb:///"):
        Path(url.removeprefix("duckdb:///")).parent.mkdir(parents=True, exist_ok=True)
        # A pooled connection per checkout (not per thread): SingletonThreadPool closes other threads'
        # connections, even ones in use, once more than pool_size threads have touched the catalog.
        # A checkpoint at every commit: after a crash DuckDB 1.5 can replay its write-ahead log into
        # secondary indexes that then refuse to update the row ("Failed to delete all rows from
        # index", a FATAL error that invalidates the database); with no log left there is none to replay.
        skip_missing_pandas()
        engine = sa.create_engine(
            url, pool_size=5, max_overflow=20, connect_args={"config": {"checkpoint_threshold": "0b"}}
        )
        sa.event.listen(engine, "handle_error", _embedded_catalog_locked)
        return engine
    if url.startswith("postgresql"):
        return _postgres_engine(url, timeout_s)
    raise UnavailableError(f"unsupported catalog URL {url!r}: use duckdb:///PATH or postgresql+psycopg://USER@HOST/DB")


def _postgres_engine(url: str, timeout_s: float | None) -> sa.Engine:
    """With `timeout_s` (FLEET_CATALOG_TIMEOUT_S), every call has a deadline: the connect, the wait
    for a pooled connection, and each statement (Postgres cancels it: an OperationalError, answered
    UNAVAILABLE). Without (migrations), only the connect has one."""
    connect_args: dict[str, object] = {"connect_timeout": CONNECT_TIMEOUT_S}
    if timeout_s is None:
        return sa.create_engine(url, pool_pre_ping=True, connect_args=connect_args)
    connect_args["connect_timeout"] = max(1, min(CONNECT_TIMEOUT_S, math.ceil(timeout_s)))
    connect_args["options"] = f"-c statement_timeout={int(timeout_s * 1000)}"
    return sa.create_engine(url, pool_pre_ping=True, pool_timeout=timeout_s, connect_args=connect_args)


class _NoPandas:
    """An import finder that fails `import pandas` at once (see `skip_missing_pandas`)."""

    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        if name == "pandas":
            raise ModuleNotFoundError("No module named 'pandas'", name="pandas")


def skip_missing_pandas() -> None:
    """DuckDB's Python driver tries `import pandas` for every bound parameter of every query (to
    tell pandas objects apart); without pandas installed, each failed import searches the whole
    `sys.path` again, which made a catalog query on DuckDB ~5x slower (benchmarks/duckdb_params.py).
    When pandas is not installed, fail that import at once instead; a pandas installed later is
    seen after a restart. tests/catalog/test_db.py pins the driver behaviour this assumes."""
    if any(isinstance(f, _NoPandas) for f in sys.meta_path):
        return
    try:
        missing = importlib.util.find_spec("pandas") is None
    except ImportError:  # another finder already refuses it
        missing = False
    if missing:
        sys.meta_path.insert(0, _NoPandas())


_LOCK_HOLDER = re.compile(r"Could not set lock on file .*\(PID (\d+)\)", re.DOTALL)


def _embedded_catalog_locked(context: sa.engine.ExceptionContext) -> None:
    """DuckDB lets one process at a time open its file; the process that cannot gets a long
    driver error (a traceback through the CLI). Say instead who holds it and what to do."""
    holder = _LOCK_HOLDER.search(str(context.original_exception))
    if holder is not None:
        raise ConflictError(
            f"the embedded catalog is in use by another process (PID {holder.group(1)}, probably a running "
            "`fleet serve`): stop it first; DuckDB lets one process at a time open the file (several "
            "processes can share a Postgres catalog)"
        ) from None


def locks_rows(session: Session) -> bool:
    """Postgres locks rows read for update; the embedded catalog has one writer and no such clause."""
    return session.get_bind().dialect.name == "postgresql"


def is_embedded(engine: sa.Engine) -> bool:
    return engine.dialect.name == "duckdb"


_WRITERS: dict[str, threading.RLock] = {}
_WRITERS_GUARD = threading.Lock()


def _writer_lock(factory: sessionmaker[Session]) -> threading.RLock | None:
    """The embedded catalog's one-writer-at-a-time lock (None for Postgres, which locks rows itself).

    DuckDB checks write-write conflicts optimistically: two transactions that update the same row
    (a run, its robot) fail the second with "Conflict on update!" even when they touch it one after
    the other, if the second began before the first committed. Writers therefore take this lock for
    their whole transaction, so each begins after the previous one committed."""
    bind = factory.kw.get("bind")
    if not isinstance(bind, sa.Engine) or not is_embedded(bind):
        return None
    key = str(bind.url)
    with _WRITERS_GUARD:
        return _WRITERS.setdefault(key, threading.RLock())


@contextmanager
def session_scope(factory: sessionmaker[Session], *, write: bool = False) -> Iterator[Session]:
    """The one way to use the catalog: a session committed on success, rolled back on error.
    `write=True` for a session that changes anything (serialized on the embedded catalog)."""
    lock = _writer_lock(factory) if write else None
    with lock if lock is not None else nullcontext():
        session = factory()
        try:
            yield session
            session.commit()
        except BaseException:
            session.rollback()
            raise
        finally:
            session.close()


def alembic_config(engine: sa.Engine | None = None) -> Config:
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    if engine is not None:
        config.attributes["connection_engine"] = engine
    return config


def head_revision() -> str:
    heads = ScriptDirectory.from_config(alembic_config()).get_heads()
    if len(heads) != 1:
        raise UnavailableError(f"migrations have {len(heads)} heads ({', '.join(heads)}); expected one")
    return heads[0]


def current_revision(engine: sa.Engine) -> str | None:
    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def upgrade(engine: sa.Engine) -> tuple[str | None, str]:
    """Bring the catalog to the head revision; returns (before, after)."""
    from alembic import command

    before = current_revision(engine)
    with engine.begin() as conn:
        config = alembic_config()
        config.attributes["connection"] = conn
        command.upgrade(config, "head")
    return before, head_revision()


def check_schema(engine: sa.Engine) -> None:
    """Raise UnavailableError (one line naming the fix) unless the catalog is at the head revision."""
    current, head = current_revision(engine), head_revision()
    if current != head:
        state = "empty" if current is None else f"at revision {current}"
        raise UnavailableError(f"the catalog is {state}, the service needs {head}: run `fleet db upgrade`")


def prepare_for_service(engine: sa.Engine) -> str | None:
    """At service start: an embedded catalog is created or upgraded (returns what was done, to be
    said); any other catalog must already be at head (UnavailableError naming `fleet db upgrade`)."""
    if not is_embedded(engine):
        check_schema(engine)
        return None
    before = current_revision(engine)
    if before == head_revision():
        return None
    _, after = upgrade(engine)
    url = engine.url.render_as_string(hide_password=True)
    if before is None:
        return f"created the embedded catalog {url} at revision {after}"
    return f"upgraded the embedded catalog {url} from revision {before} to {after}"
