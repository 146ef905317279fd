"""Fixtures shared by every test package."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import create_engine, upgrade
from services.compiled import compiled_modules
from services.runtime import drop_realtime, process_threads
from tests.postgres import database_name, temporary_database
from tests.services.rrd.recordings import SCENES, Recording, cut_mid_arrow, generate_scenes, rerun_rrd

# Every depot a test starts (in process or as `fleet serve`, on loopback) runs with auth off unless
# the test turns it on: the suites about auth (tests/services/auth, and the end-to-end ones they
# hold) pass auth="on" themselves, and everything else tests what it is about without tokens.
os.environ["FLEET_AUTH"] = "off"
# One process per `fleet serve` (a depot on Postgres would start one worker per core): tests that
# kill or measure a depot mean that one process; tests of workers ask for them.
os.environ["FLEET_WORKERS"] = "1"


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The longest files run first, and against a compiled build (FLEET_COMPILE=1) tests that
    patch a function inside a compiled module are skipped: calls within that module go straight
    to the compiled function."""
    heavy_first(items)
    compiled = set(compiled_modules())
    for item in items:
        marker = item.get_closest_marker("interpreted")
        patched = compiled & set(marker.args) if marker is not None else set()
        if patched:
            item.add_marker(pytest.mark.skip(reason=f"patches inside {', '.join(sorted(patched))}, compiled here"))


def heavy_first(items: list[pytest.Item]) -> None:
    """Order the test files longest first, each file's tests in their own order: the workers (`-n 3
    --dist loadfile`, a file at a time, handed out in this order) start on the long files and end
    on short ones together, rather than one worker going on alone through a long file the others
    finished long before. How long a file takes is what `tests/durations.json` recorded (written by
    a run with FLEET_TEST_DURATIONS=PATH); files it does not list (new ones) come last, in their
    own order. The same order in every worker, as xdist requires."""
    recorded = recorded_durations()
    position = {item.nodeid: n for n, item in enumerate(items)}
    items.sort(key=lambda item: (-recorded.get(_file_of(item.nodeid), 0.0), position[item.nodeid]))


def recorded_durations() -> dict[str, float]:
    path = Path(__file__).parent / "durations.json"
    return {str(k): float(v) for k, v in json.loads(path.read_text()).items()} if path.exists() else {}


_file_seconds: dict[str, float] = {}


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Each test's setup, call and teardown time, summed by file (for FLEET_TEST_DURATIONS)."""
    file = _file_of(report.nodeid)
    _file_seconds[file] = _file_seconds.get(file, 0.0) + report.duration


def _file_of(nodeid: str) -> str:
    return nodeid.split("::")[0]


def pytest_sessionfinish(session: pytest.Session) -> None:
    """With FLEET_TEST_DURATIONS=PATH, write the seconds each test file took (on the controller,
    which sees every worker's reports): `tests/durations.json` is such a file, from a CI run."""
    target = os.environ.get("FLEET_TEST_DURATIONS")
    if target and not hasattr(session.config, "workerinput") and _file_seconds:
        rounded = {file: round(seconds, 1) for file, seconds in sorted(_file_seconds.items())}
        Path(target).write_text(json.dumps(rounded, indent=1) + "\n")


@pytest.fixture(autouse=True)
def no_realtime_threads() -> Iterator[None]:
    """A test leaves no thread of the test process under real-time scheduling: everything the
    process starts after (a `fleet serve`, Chromium) would inherit it, and one busy thread at
    SCHED_FIFO 99 starves the whole machine (SVT-AV1 run as root did that to the LeRobot export)."""
    yield
    found = drop_realtime(process_threads())
    if found:
        pytest.fail(f"threads {', '.join(map(str, found))} of the test process were left under real-time scheduling")


def find_rerun() -> str | None:
    """The `rerun` CLI installed next to this Python (the venv's), else the one on PATH."""
    candidate = Path(sys.executable).parent / "rerun"
    if candidate.is_file() and os.access(candidate, os.X_OK):
        return str(candidate)
    return shutil.which("rerun")


@pytest.fixture(scope="session", autouse=True)
def rerun_analytics_disabled() -> Iterator[None]:
    """Turn Rerun's analytics off once (tests must not talk to the network); failures are ignored."""
    exe = find_rerun()
    if exe is not None:
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            subprocess.run([exe, "analytics", "disable"], capture_output=True, timeout=60, check=False)
    yield


@pytest.fixture(scope="session")
def rerun_bin(rerun_analytics_disabled: None) -> str:
    """Path of the `rerun` executable (skips the test when it is not installed)."""
    exe = find_rerun()
    if exe is None:
        pytest.fail("the rerun CLI is not installed: pip install -e '.[dev]' installs rerun-sdk")
    return exe


CUT_ARROW_INDEX = 2


@pytest.fixture(scope="session")
def recordings_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("recordings")


@pytest.fixture(scope="session")
def recordings(rerun_bin: str, recordings_dir: Path) -> dict[str, Recording]:
    recs = generate_scenes(SCENES, recordings_dir)
    recs["merged"] = rerun_rrd(rerun_bin, "merge", [recs["merge_a"], recs["merge_b"]], recordings_dir, "merged")
    recs["optimized"] = rerun_rrd(rerun_bin, "optimize", [recs["points"]], recordings_dir, "optimized")
    recs["cut"] = cut_mid_arrow(recs["points"], recordings_dir, "cut", CUT_ARROW_INDEX)
    return recs


@pytest.fixture
def empty_postgres_url() -> Iterator[str]:
    """A new, empty database on the local PostgreSQL server."""
    with temporary_database("fleet_empty") as url:
        yield url


# --- catalogs: every catalog test runs against embedded DuckDB and a real Postgres ---------------


@pytest.fixture(scope="session")
def postgres_url() -> Iterator[str]:
    with temporary_database("fleet_test") as url:
        yield url


@pytest.fixture(scope="session")
def duckdb_url(tmp_path_factory: pytest.TempPathFactory) -> str:
    return f"duckdb:///{tmp_path_factory.mktemp('catalog') / 'catalog.duckdb'}"


@pytest.fixture(scope="session", params=["duckdb", pytest.param("postgres", marks=pytest.mark.postgres)])
def catalog_url(request: pytest.FixtureRequest) -> str:
    url: str = request.getfixturevalue(f"{request.param}_url")
    return url


@pytest.fixture(scope="session")
def engine(catalog_url: str) -> Iterator[sa.Engine]:
    engine = create_engine(catalog_url)
    upgrade(engine)
    yield engine
    engine.dispose()


@pytest.fixture
def session(engine: sa.Engine) -> Iterator[Session]:
    """A session inside a transaction that is rolled back after the test."""
    with engine.connect() as conn:
        outer = conn.begin()
        session = Session(bind=conn, join_transaction_mode="rollback_only")  # DuckDB has no savepoints
        try:
            yield session
        finally:
            session.close()
            outer.rollback()


# --- a migrated catalog of its own for each test of the domain suites (ingest, retention, runs,
# analytics), on both kinds: copied from one migrated once per session rather than migrated per test


@pytest.fixture(scope="session")
def migrated_duckdb_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("catalog-template") / "catalog.duckdb"
    engine = create_engine(f"duckdb:///{path}")
    upgrade(engine)
    engine.dispose()  # every commit is checkpointed (catalog.db): the file alone is the database
    return path


@pytest.fixture(scope="session")
def migrated_postgres_template() -> Iterator[str]:
    """The name of a migrated database no one stays connected to (CREATE DATABASE ... TEMPLATE needs that)."""
    with temporary_database("fleet_template") as url:
        engine = create_engine(url)
        upgrade(engine)
        engine.dispose()
        yield database_name(url)


@contextlib.contextmanager
def fresh_catalog(kind: str, request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A migrated catalog for one test alone (`kind` duckdb or postgres): a copy of the DuckDB
    template file, or a Postgres database created from the migrated template."""
    if kind == "duckdb":
        path = tmp_path / "catalog.duckdb"
        shutil.copyfile(request.getfixturevalue("migrated_duckdb_template"), path)
        yield f"duckdb:///{path}"
        return
    with temporary_database("fleet_test", template=request.getfixturevalue("migrated_postgres_template")) as url:
        yield url


CATALOG_KINDS = ["duckdb", pytest.param("postgres", marks=pytest.mark.postgres)]


@pytest.fixture(params=CATALOG_KINDS)
def fresh_catalog_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    with fresh_catalog(request.param, request, tmp_path) as url:
        yield url


@pytest.fixture
def catalog(fresh_catalog_url: str) -> Iterator[sessionmaker[Session]]:
    """Sessions on a migrated catalog of this test's own, of each kind (a module that means
    something else by `catalog` defines its own)."""
    engine = create_engine(fresh_catalog_url)
    try:
        yield sessionmaker(engine)
    finally:
        engine.dispose()


@pytest.fixture
def empty_catalog_url(catalog_url: str, tmp_path: Path) -> Iterator[str]:
    """A catalog with no schema at all, of the same kind."""
    if catalog_url.startswith("duckdb"):
        yield f"duckdb:///{tmp_path / 'empty.duckdb'}"
        return
    with temporary_database("fleet_empty") as url:
        yield url
