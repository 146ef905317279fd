"""What `catalog.db.skip_missing_pandas` assumes of DuckDB's driver, and what it does."""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(importlib.util.find_spec("pandas") is not None, reason="pandas is installed here")

PROBE = """
import sys, duckdb
tried = []
class Spy:
    def find_spec(self, name, path=None, target=None):
        tried.append(name)
sys.meta_path.insert(0, Spy())
connection = duckdb.connect()
connection.execute("CREATE TABLE t (a VARCHAR)")
connection.execute("SELECT * FROM t WHERE a = ? OR a = ?", ["x", "y"]).fetchall()
print(tried.count("pandas"))
"""


def test_duckdb_tries_to_import_pandas_for_each_bound_parameter():
    # The day this prints 0 the shim is no longer needed: remove skip_missing_pandas.
    tried = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True)
    assert int(tried.stdout) >= 2


def test_without_pandas_the_import_fails_at_once_and_queries_still_work(tmp_path):
    script = f"""
import sys
from catalog.db import create_engine, skip_missing_pandas
import sqlalchemy as sa
engine = create_engine("duckdb:///{tmp_path / "c.duckdb"}")
skip_missing_pandas()  # twice: installed once
assert sum(type(f).__name__ == "_NoPandas" for f in sys.meta_path) == 1
try:
    import pandas
except ModuleNotFoundError as exc:
    assert exc.name == "pandas"
with engine.connect() as c:
    assert c.execute(sa.text("SELECT :a"), {{"a": 7}}).scalar() == 7
import pyarrow as pa
assert pa.table({{"a": [1]}}).num_rows == 1  # pyarrow does not mistake the shim for pandas
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert done.stdout.strip() == "ok", done.stderr
