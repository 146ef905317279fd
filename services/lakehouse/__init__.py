"""The lakehouse: the analytics tables as Apache Iceberg tables that outside engines read (Trino,
Spark, DuckDB, pyiceberg), kept by the depot: `tables.py` (the catalog and tables), `schemas.py`
(their schemas, and a run's rows made to fit them), `sync.py` (runs' rows copied exactly once)."""
