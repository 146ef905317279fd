"""Keeping the lakehouse's tables fast and its bucket clean: small files compacted, old snapshots
expired, and files no snapshot reaches any more removed (a deleted run's rows with them).

Compaction streams a partition's small files into one, a record batch at a time (memory: a row group
of the largest input), and swaps them in one commit that names the files it replaces: a run
replaced or deleted meanwhile makes the commit fail validation and the partition waits for the next
pass, so compaction never brings back or loses a row. Orphans are files under a table's folder that
no kept snapshot or metadata file names and that are older than the snapshots kept (a commit under
way elsewhere is never that old).
"""

from __future__ import annotations

import datetime as dt
import logging
import uuid
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING
from urllib.parse import urlparse

import pyarrow as pa
import pyarrow.parquet as pq

from services.lakehouse.tables import Lakehouse
from services.storage.objectstore import ObjectStore

# pyiceberg (and the schemas, made of its types) is imported by the steps that use it: a third of a
# second a depot's start does not pay (services.lakehouse.tables)
if TYPE_CHECKING:
    from pyiceberg.manifest import DataFile
    from pyiceberg.table import Table

log = logging.getLogger(__name__)

JOB = "lakehouse.maintenance"
SMALL_FILE_BYTES = 32 * 1024 * 1024  # files under this are compacted together
MIN_FILES = 4  # a partition with fewer small files is left as it is
GROUP_BYTES = 256 * 1024 * 1024  # most input a compacted file takes


@dataclass(frozen=True)
class MaintenanceReport:
    compacted_files: int  # small files replaced
    written_files: int  # files they became
    expired_snapshots: int
    removed_files: int  # files no snapshot reached


def maintain(lake: Lakehouse, warm: ObjectStore, now: dt.datetime, keep: dt.timedelta) -> MaintenanceReport:
    """One pass over every table: compact, expire snapshots older than `keep`, remove orphans."""
    from services.lakehouse.schemas import TABLES

    totals = [0, 0, 0, 0]
    for name in TABLES:
        replaced, written = compact(lake.table(name))
        expired = expire_snapshots(lake.table(name), now - keep)
        removed = remove_orphans(lake.table(name), warm, now - keep)
        for i, n in enumerate((replaced, written, expired, removed)):
            totals[i] += n
    return MaintenanceReport(*totals)


def compact(table: Table) -> tuple[int, int]:
    """Each partition's small files, in groups of up to GROUP_BYTES, rewritten as one file each;
    returns (files replaced, files written)."""
    by_partition: dict[tuple[object, ...], list[DataFile]] = defaultdict(list)
    for task in table.scan().plan_files():
        if task.file.file_size_in_bytes < SMALL_FILE_BYTES and not task.delete_files:
            by_partition[_partition_key(task.file)].append(task.file)
    replaced = written = 0
    for files in by_partition.values():
        if len(files) < MIN_FILES:
            continue
        for group in _groups(sorted(files, key=lambda f: f.file_path)):
            if len(group) < 2:
                continue
            if _rewrite(table, group):
                replaced, written = replaced + len(group), written + 1
            table = table.refresh()
    return replaced, written


def _partition_key(data_file: DataFile) -> tuple[object, ...]:
    record = data_file.partition
    return tuple(record[i] for i in range(len(record)))


def _groups(files: list[DataFile]) -> Iterable[list[DataFile]]:
    group: list[DataFile] = []
    size = 0
    for data_file in files:
        if group and size + data_file.file_size_in_bytes > GROUP_BYTES:
            yield group
            group, size = [], 0
        group.append(data_file)
        size += data_file.file_size_in_bytes
    if group:
        yield group


def _rewrite(table: Table, group: list[DataFile]) -> bool:
    """Write `group`'s rows to one new file and swap it in; False if another writer changed one of
    them first (the new file is removed: the next pass looks again)."""
    from pyiceberg.exceptions import CommitFailedException, ValidationException
    from pyiceberg.io.pyarrow import parquet_file_to_data_file, schema_to_pyarrow

    arrow_schema = schema_to_pyarrow(table.schema())  # with the field ids every engine reads by
    partition_path = table.spec().partition_to_path(group[0].partition, table.schema())
    path = f"{table.location()}/data/{partition_path}/compacted-{uuid.uuid4()}.parquet"
    with table.io.new_output(path).create() as out, pq.ParquetWriter(out, arrow_schema, compression="zstd") as writer:
        for data_file in group:
            with table.io.new_input(data_file.file_path).open() as source:
                for batch in pq.ParquetFile(source).iter_batches():
                    writer.write_batch(_conform(batch, arrow_schema))
    try:
        new = parquet_file_to_data_file(table.io, table.metadata, path)
        with table.transaction() as tx, tx.update_snapshot().overwrite() as swap:
            for data_file in group:
                swap.delete_data_file(data_file)
            swap.append_data_file(new)
        return True
    except (CommitFailedException, ValidationException) as exc:
        log.info("lakehouse: compaction of %s left for the next pass (%s)", partition_path, exc)
        table.io.delete(path)
        return False


def _conform(batch: pa.RecordBatch, schema: pa.Schema) -> pa.RecordBatch:
    """A batch of a file written under an older schema as one of `schema` (new columns null)."""
    columns = [
        batch.column(f.name).cast(f.type) if f.name in batch.schema.names else pa.nulls(batch.num_rows, f.type)
        for f in schema
    ]
    return pa.RecordBatch.from_arrays(columns, schema=schema)


def expire_snapshots(table: Table, before: dt.datetime) -> int:
    """Forget the snapshots made before `before` (never the current one)."""
    from pyiceberg.exceptions import CommitFailedException

    current = table.current_snapshot()
    old = [
        s.snapshot_id
        for s in table.metadata.snapshots
        if s.timestamp_ms < before.timestamp() * 1000 and (current is None or s.snapshot_id != current.snapshot_id)
    ]
    if old:
        try:
            table.maintenance.expire_snapshots().by_ids(old).commit()
        except CommitFailedException as exc:
            log.info("lakehouse: snapshots of %s expire on the next pass (%s)", table.name(), exc)
            return 0
    return len(old)


def remove_orphans(table: Table, warm: ObjectStore, before: dt.datetime) -> int:
    """Remove files under the table's folder that nothing kept names and that are older than `before`."""
    table = table.refresh()
    reached = _reachable(table)
    prefix = _key(warm, table.location())
    if prefix is None:
        return 0
    removed = 0
    for info in list(warm.list(prefix.rstrip("/") + "/")):
        if info.last_modified >= before or _location(warm, info.key) in reached:
            continue
        warm.delete(info.key)
        removed += 1
    return removed


def _reachable(table: Table) -> set[str]:
    """Every file the table's kept metadata names: metadata files, manifest lists, manifests, data."""
    metadata = table.metadata
    found = {_normal(table.metadata_location), *(_normal(m.metadata_file) for m in metadata.metadata_log)}
    for snapshot in metadata.snapshots:
        found.add(_normal(snapshot.manifest_list))
        for manifest in snapshot.manifests(table.io):
            found.add(_normal(manifest.manifest_path))
            for entry in manifest.fetch_manifest_entry(table.io):  # a DELETED entry: gone in that snapshot
                found.add(_normal(entry.data_file.file_path))
    for statistics in metadata.statistics:
        found.add(_normal(statistics.statistics_path))
    return found


def _normal(location: str) -> str:
    parsed = urlparse(location)
    return f"{parsed.scheme or 'file'}://{parsed.netloc}{parsed.path}"


def _key(warm: ObjectStore, location: str) -> str | None:
    """The warm store's key of a location under it (None if it is elsewhere)."""
    base = _normal(warm.url).rstrip("/") + "/"
    found = _normal(location)
    return found[len(base) :] if found.startswith(base) else None


def _location(warm: ObjectStore, key: str) -> str:
    return _normal(warm.url).rstrip("/") + "/" + key
