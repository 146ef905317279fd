"""`fleet analytics migrate`: analytics files written before the lakehouse copied into its tables,
with progress, and nothing copied twice when run again."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pyarrow.compute as pc
import pytest
from sqlalchemy.orm import sessionmaker

from catalog.db import create_engine
from catalog.db import upgrade as upgrade_catalog
from services.lakehouse.tables import open_lakehouse
from services.storage.objectstore import open_store
from tests.services.analytics.conftest import catalog_run, write_scalars

FLEET = str(Path(sys.executable).with_name("fleet"))
pytestmark = pytest.mark.slow


def _fleet(data: Path, *args: str, **more: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "FLEET_DATA_DIR": str(data), **more}
    return subprocess.run([FLEET, *args], capture_output=True, text=True, timeout=120, env=env)


def test_migrate_copies_files_written_before_the_lakehouse_once(tmp_path: Path) -> None:
    data = tmp_path / "data"
    url = f"duckdb:///{data / 'catalog.duckdb'}"
    data.mkdir()
    engine = create_engine(url)
    upgrade_catalog(engine)
    warm = open_store((data / "warm").as_uri())
    for i, robot in enumerate(("robot-1", "robot-2", "robot-2")):
        key = write_scalars(warm, robot, "2026-03-01", f"old-run-{i}", [float(i)] * (i + 2))
        catalog_run(sessionmaker(engine), f"old-run-{i}", robot, "2026-03-01", {"analytics/scalars": key})
    engine.dispose()  # the embedded catalog: one process at a time

    first = _fleet(data, "analytics", "migrate")
    assert first.returncode == 0, first.stderr
    assert "3 runs to copy" in first.stdout and "done: 3 runs copied, 9 rows" in first.stdout
    again = _fleet(data, "analytics", "migrate")
    assert again.returncode == 0 and "0 runs to copy" in again.stdout and "done: 0 runs copied" in again.stdout

    lake = open_lakehouse(url, warm)
    try:
        rows = lake.table("scalars").scan().to_arrow()
    finally:
        lake.close()
    counts = {c["values"]: c["counts"] for c in pc.value_counts(rows["run_id"]).to_pylist()}
    assert counts == {"old-run-0": 2, "old-run-1": 3, "old-run-2": 4}
    assert sorted(set(zip(rows["run_id"].to_pylist(), rows["robot_id"].to_pylist(), strict=True))) == [
        ("old-run-0", "robot-1"),
        ("old-run-1", "robot-2"),
        ("old-run-2", "robot-2"),
    ]


def test_migrate_refuses_when_the_lakehouse_is_off_or_the_catalog_is_not_upgraded(tmp_path: Path) -> None:
    off = _fleet(tmp_path, "analytics", "migrate", FLEET_LAKEHOUSE="false")
    assert off.returncode == 1 and "FLEET_LAKEHOUSE=false" in off.stderr and off.stderr.strip().count("\n") == 0
    old = _fleet(tmp_path, "analytics", "migrate")
    assert old.returncode == 1 and "fleet db upgrade" in old.stderr and old.stderr.strip().count("\n") == 0
