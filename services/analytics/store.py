"""Where the analytics tables live: Parquet under `analytics/TABLE/robot_id=R/date=D/RUN.parquet`
in the warm store, one file per run and table (Hive partitions: robot and date prune reads)."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from pathlib import Path

from catalog.queries import ObjectRecord
from core.states import Tier
from services.analytics.extract import partition_key
from services.storage.objectstore import ObjectStore


def write_analytics(
    store: ObjectStore, files: Mapping[str, Path], run_id: str, robot_id: str, date: str
) -> list[ObjectRecord]:
    """Upload a run's analytics tables (`Extractor.files()`: each table's Parquet file); returns them
    as objects of the run (deleted with it)."""
    objects = []
    for table, path in files.items():
        with open(path, "rb") as fh:
            sha256 = hashlib.file_digest(fh, "sha256").hexdigest()
            fh.seek(0)
            key = partition_key(table, robot_id, date, run_id)
            store.put(key, fh)
        objects.append(ObjectRecord(f"analytics/{table}", key, Tier.WARM, path.stat().st_size, sha256))
    return objects
