"""The local PostgreSQL server for tests: fresh databases created and dropped on demand."""

from __future__ import annotations

import os
import subprocess
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

import sqlalchemy as sa
from sqlalchemy.orm import Session

PG_ADMIN_URL = os.environ.get("FLEET_TEST_PG_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")


def admin_engine() -> sa.Engine:
    engine = sa.create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    try:
        with engine.connect():
            return engine
    except sa.exc.OperationalError:
        # The machine's server may be stopped: start it (as the developers' guide says), once.
        versions = os.listdir("/etc/postgresql") if os.path.isdir("/etc/postgresql") else []
        if versions:
            subprocess.run(
                ["pg_ctlcluster", "--skip-systemctl-redirect", versions[0], "main", "start"],
                check=False,
                capture_output=True,
                timeout=60,
            )
        with engine.connect():
            return engine


def database_url(name: str) -> str:
    return PG_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"


def database_name(url: str) -> str:
    return url.rsplit("/", 1)[1]


@contextmanager
def temporary_database(prefix: str, *, template: str | None = None) -> Iterator[str]:
    """The URL of a new database, dropped afterwards: empty, or a copy of `template` (a database
    no one is connected to, so Postgres can copy it file by file)."""
    admin = admin_engine()
    name = f"{prefix}_{uuid.uuid4().hex[:12]}"
    with admin.connect() as conn:
        conn.execute(sa.text(f'CREATE DATABASE "{name}"' + (f' TEMPLATE "{template}"' if template else "")))
    try:
        yield database_url(name)
    finally:
        with admin.connect() as conn:
            conn.execute(sa.text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


@contextmanager
def index_only_session(url: str) -> Iterator[Session]:
    """A session on the Postgres catalog at `url`, migrated, in a transaction rolled back afterwards,
    where the planner may neither scan a table whole nor sort: a statement that cannot be answered
    from an index then shows it in its plan."""
    from catalog.db import create_engine, upgrade

    engine = create_engine(url)
    upgrade(engine)
    with engine.connect() as conn:
        outer = conn.begin()
        conn.exec_driver_sql("SET LOCAL enable_seqscan = off")
        conn.exec_driver_sql("SET LOCAL enable_sort = off")
        session = Session(bind=conn, join_transaction_mode="rollback_only")
        try:
            yield session
        finally:
            session.close()
            outer.rollback()
            engine.dispose()
