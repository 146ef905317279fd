"""Where the analytics tables live: Parquet under `analytics/TABLE/robot_id=R/date=D/RUN.parquet`
in the warm store, one file per run and table (Hive partitions: robot and date prune reads)."""

from __future__ import annotations

import hashlib

from catalog.queries import ObjectRecord
from core.states import Tier
from services.analytics.extract import Extractor, partition_key, to_parquet
from services.storage.objectstore import ObjectStore


def write_analytics(store: ObjectStore, extractor: Extractor, robot_id: str, date: str) -> list[ObjectRecord]:
    """Upload a run's analytics tables; returns them as objects of the run (deleted with it)."""
    objects = []
    for table, rows in extractor.tables().items():
        data = to_parquet(rows)
        key = partition_key(table, robot_id, date, extractor.run_id)
        store.put(key, data)
        objects.append(ObjectRecord(f"analytics/{table}", key, Tier.WARM, len(data), hashlib.sha256(data).hexdigest()))
    return objects
