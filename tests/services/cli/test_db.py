import subprocess
import sys
from pathlib import Path

import pytest

from catalog.db import head_revision

FLEET = str(Path(sys.executable).with_name("fleet"))


def _fleet(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([FLEET, *args], capture_output=True, text=True, timeout=60)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["duckdb", pytest.param("postgres", marks=pytest.mark.postgres)])
def test_db_upgrade_then_current(kind: str, tmp_path: Path, request: pytest.FixtureRequest):
    url = f"duckdb:///{tmp_path / 'c.duckdb'}" if kind == "duckdb" else request.getfixturevalue("empty_postgres_url")
    head = head_revision()
    assert f"catalog at (empty), this release needs {head}" in _fleet("db", "current", "--catalog-url", url).stdout
    first = _fleet("db", "upgrade", "--catalog-url", url)
    assert first.returncode == 0 and f"upgraded from revision (empty) to {head}" in first.stdout
    again = _fleet("db", "upgrade", "--catalog-url", url)
    assert again.returncode == 0 and f"already at revision {head}" in again.stdout
    assert f"catalog at {head}" in _fleet("db", "current", "--catalog-url", url).stdout


def test_db_upgrade_bad_url_is_one_line():
    result = _fleet("db", "upgrade", "--catalog-url", "mysql://x/y")
    assert result.returncode == 1
    assert result.stderr.strip().count("\n") == 0 and "postgresql+psycopg" in result.stderr


@pytest.mark.slow
def test_db_recount_counts_runs_written_without_counting(tmp_path: Path):
    """A run an older release wrote (no count) is in its dataset's columns once `fleet db recount` ran."""
    import datetime as dt

    import sqlalchemy as sa
    from sqlalchemy.orm import Session

    from catalog.dataset_columns import dataset_columns
    from catalog.db import create_engine
    from catalog.models import DatasetColumn
    from catalog.queries import TimelineRecord, save_run
    from tests.catalog.records import run_record

    url = f"duckdb:///{tmp_path / 'c.duckdb'}"
    assert _fleet("db", "recount", "--catalog-url", url).returncode == 1  # not at head: says to upgrade
    assert _fleet("db", "upgrade", "--catalog-url", url).returncode == 0
    engine = create_engine(url)
    with Session(engine) as session, session.begin():
        record = run_record("run-1", timelines=[TimelineRecord("frame", "sequence", 0, 9)])
        save_run(session, record, dt.datetime.now(dt.UTC))
        session.info.clear()  # as an older release writes it: nothing counted
        session.execute(sa.delete(DatasetColumn))
    engine.dispose()  # the embedded catalog: one process at a time
    recount = _fleet("db", "recount", "--catalog-url", url)
    assert recount.returncode == 0 and "of 1 runs again" in recount.stdout, recount.stderr
    engine = create_engine(url)
    try:
        with Session(engine) as session:
            assert dataset_columns(session, "nav").timelines == {"frame": "sequence"}
    finally:
        engine.dispose()
