"""An analyst's tools in a virtualenv of their own, created on demand and cached outside the clone,
for the tests that read the lakehouse's Iceberg tables as an outside engine does
(tests/services/lakehouse/test_outside_engines.py): pyiceberg with its SQL catalog on Postgres,
and DuckDB with its iceberg, avro and httpfs extensions from their wheels.

    python -m tests.compat.lakehouse_venv      create it if missing (CI does, beside its other installs)

Why a venv of its own: an analyst's machine has none of the depot's code or credentials; reading the
tables from here shows they need neither. Bump NAME when REQUIREMENTS change.
"""

from __future__ import annotations

from pathlib import Path

from tests.compat.tool_venvs import ToolVenv

NAME = "lakehouse-reader-1"
REQUIREMENTS = [
    "pyiceberg[pyarrow,sql-postgres]==0.12.0",
    "duckdb==1.5.5",
    "duckdb-extension-iceberg==1.5.5",
    "duckdb-extension-avro==1.5.5",
    "duckdb-extension-httpfs==1.5.5",
]
IMPORT = "import pyiceberg.catalog.sql, psycopg2, duckdb, duckdb_extension_iceberg, duckdb_extension_httpfs"


VENV = ToolVenv(NAME, tuple(REQUIREMENTS), IMPORT, timeout_s=900)


def lakehouse_python() -> Path:
    """The venv's python (created if missing)."""
    return VENV.python()


if __name__ == "__main__":
    print(lakehouse_python())
