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
