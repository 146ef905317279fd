"""Analytics tables extracted from a run's chunks: scalars, text logs and transforms, as Parquet.

One pass over the chunks (the same pass that seals the run); only chunks holding one of these
archetypes are decoded. Sealing writes each table to a Parquet file as its rows come, SPILL_ROWS at
a time, so its memory does not grow with the run (`Extractor(spill_dir=...)`); queries over a hot
run keep them in memory. Every table has `run_id`, `entity`, `log_time` and one column per other
timeline of the run (named after it; `timeline_NAME` if the name is taken). Robot and date are
not stored in the files: they are the Hive partition (`robot_id=R/date=D/`) the file lies in.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from services.hot.read import read_events
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.errors import InvalidChunkError
from services.rrd.fieldmeta import component_name
from services.rrd.messages import ArrowMessage, StoreKind
from services.rrd.validate import validated_batch
from services.rrd.values import (
    AXIS_ANGLE,
    LEVEL,
    QUATERNION,
    TEXT,
    TRANSLATION,
    axis_angle_quaternions,
    first_instances,
    timelines,
    vectors,
)
from services.rrd.values import (
    SCALARS as SCALARS,  # the scalars table's component, which analytics' users import from here
)

log = logging.getLogger(__name__)

TABLES = ("scalars", "text_logs", "transforms")
PARTITION_COLUMNS = ("robot_id", "date")  # the Hive partition: no file column may take these names
LOG_TIME = "log_time"

FIXED_COLUMNS = {
    "scalars": ("run_id", "entity", "component", "instance", "value"),
    "text_logs": ("run_id", "entity", "level", "text"),
    "transforms": ("run_id", "entity", "tx", "ty", "tz", "qx", "qy", "qz", "qw"),
}


def _interesting(meta: ChunkMeta) -> bool:
    names = meta.component_names
    return SCALARS in names or TEXT in names or TRANSLATION in names or QUATERNION in names or AXIS_ANGLE in names


# Rows of a table held before they go to its file: a copy of them, and the chunks their columns came
# from (their values are slices of the chunk's buffers until the copy), a few MB.
SPILL_ROWS = 1 << 16


class Extractor:
    """Collects the analytics rows of one run, chunk by chunk: in memory (`tables()`), or written to
    Parquet files in `spill_dir` as they come (`files()`)."""

    def __init__(self, run_id: str, spill_dir: Path | None = None) -> None:
        self.run_id = run_id
        self._tables = {t: _TableRows(spill_dir / f"{t}.parquet" if spill_dir else None) for t in TABLES}

    def add(self, msg: ArrowMessage, meta: ChunkMeta) -> None:
        if meta.is_static or not _interesting(meta) or meta.entity_path.startswith("/__properties"):
            return
        try:
            batch = validated_batch(msg, meta)  # values are read below: never out of bounds
        except InvalidChunkError as exc:
            # Ingest refuses such chunks; one stored before it did must not stop the run's sealing.
            log.warning("run %s: analytics skip %s", self.run_id, exc)
            return
        columns = {_component(f): batch.column(i) for i, f in enumerate(batch.schema)}
        times = timelines(batch)
        if SCALARS in columns:
            self._scalars(meta.entity_path, columns[SCALARS], times)
        if TEXT in columns:
            self._text_logs(meta.entity_path, columns[TEXT], columns.get(LEVEL), times)
        if TRANSLATION in columns or QUATERNION in columns or AXIS_ANGLE in columns:
            self._transforms(meta.entity_path, columns, times)

    def append(self, table: str, rows: pa.Table) -> None:
        """Rows of one of the TABLES, as extraction makes them."""
        self._tables[table].add(rows)

    def _scalars(self, entity: str, column: pa.Array, times: dict[str, pa.Array]) -> None:
        values = pc.list_flatten(column)
        if len(values) == 0:
            return
        rows = pc.list_parent_indices(column).to_numpy()
        offsets = np.asarray(column.offsets)
        instance = np.arange(len(values), dtype=np.int64) + offsets[0] - offsets[rows]
        n = len(values)
        self._emit(
            "scalars",
            {
                "run_id": pa.array([self.run_id] * n, pa.string()),
                "entity": pa.array([entity] * n, pa.string()),
                "component": pa.array([SCALARS] * n, pa.string()),
                "instance": pa.array(instance.astype(np.int32)),
                "value": pc.cast(values, pa.float64()),
            },
            times,
            rows,
        )

    def _text_logs(self, entity: str, text: pa.Array, level: pa.Array | None, times: dict[str, pa.Array]) -> None:
        texts, has = first_instances(text)
        rows = np.flatnonzero(has)
        if len(rows) == 0:
            return
        levels = first_instances(level)[0] if level is not None else pa.nulls(len(text), pa.string())
        n = len(rows)
        self._emit(
            "text_logs",
            {
                "run_id": pa.array([self.run_id] * n, pa.string()),
                "entity": pa.array([entity] * n, pa.string()),
                "level": levels.take(pa.array(rows)),
                "text": texts.take(pa.array(rows)),
            },
            times,
            rows,
        )

    def _transforms(self, entity: str, columns: dict[str, pa.Array], times: dict[str, pa.Array]) -> None:
        length = len(next(iter(times.values()))) if times else len(next(iter(columns.values())))
        translation, has_t = vectors(columns.get(TRANSLATION), 3, length)
        rotation, has_r = vectors(columns.get(QUATERNION), 4, length)
        if AXIS_ANGLE in columns:
            axis_angle, has_aa = axis_angle_quaternions(columns[AXIS_ANGLE], length)
            rotation = np.where(has_aa[:, None] & ~has_r[:, None], axis_angle, rotation)
            has_r = has_r | has_aa
        rows = np.flatnonzero(has_t | has_r)
        if len(rows) == 0:
            return
        n = len(rows)
        out: dict[str, pa.Array] = {
            "run_id": pa.array([self.run_id] * n, pa.string()),
            "entity": pa.array([entity] * n, pa.string()),
        }
        for i, name in enumerate(("tx", "ty", "tz")):
            out[name] = pa.array(translation[rows, i], pa.float64(), mask=~has_t[rows])
        for i, name in enumerate(("qx", "qy", "qz", "qw")):
            out[name] = pa.array(rotation[rows, i], pa.float64(), mask=~has_r[rows])
        self._emit("transforms", out, times, rows)

    def _emit(self, table: str, columns: dict[str, pa.Array], times: dict[str, pa.Array], rows: np.ndarray) -> None:
        taken = pa.array(rows.astype(np.int64))
        for name, values in times.items():
            clash = name in FIXED_COLUMNS[table] or name in PARTITION_COLUMNS
            column = f"timeline_{name}" if clash and name != LOG_TIME else name
            columns[column] = values.take(taken)
        self.append(table, pa.table(columns))

    def tables(self) -> dict[str, pa.Table]:
        """Each non-empty table, its per-chunk pieces unified (runs may add timelines as they go)."""
        tables = {name: rows.table() for name, rows in self._tables.items()}
        return {name: table for name, table in tables.items() if table is not None}

    def files(self) -> dict[str, Path]:
        """Each non-empty table's Parquet file, finished (spilling extractors only)."""
        files = {name: rows.finish() for name, rows in self._tables.items()}
        return {name: path for name, path in files.items() if path is not None}


class _TableRows:
    """One table's rows: held, or written to `path` SPILL_ROWS at a time. A piece whose columns differ
    from the file's (a timeline that appeared later) starts a part file of its own; `finish` merges
    the parts into one file with every column, a row group at a time."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._held: list[pa.Table] = []
        self._held_rows = 0
        self._parts: list[Path] = []
        self._writer: pq.ParquetWriter | None = None

    def add(self, rows: pa.Table) -> None:
        self._held.append(rows)
        self._held_rows += rows.num_rows
        if self.path is not None and self._held_rows >= SPILL_ROWS:
            self._spill()

    def table(self) -> pa.Table | None:
        return pa.concat_tables(self._held, promote_options="permissive") if self._held else None

    def _spill(self) -> None:
        assert self.path is not None
        table = pa.concat_tables(self._held, promote_options="permissive").combine_chunks()  # a copy
        self._held, self._held_rows = [], 0
        if self._writer is None or not self._writer.schema.equals(table.schema):
            self._close_part()
            part = self.path.with_name(f"{self.path.stem}.part{len(self._parts)}")
            self._parts.append(part)
            self._writer = pq.ParquetWriter(part, table.schema, compression="zstd")
        self._writer.write_table(table)

    def _close_part(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def finish(self) -> Path | None:
        assert self.path is not None, "files() is for an Extractor with a spill_dir"
        if self._held:
            self._spill()
        self._close_part()
        if not self._parts:
            return None
        if len(self._parts) == 1:
            self._parts[0].replace(self.path)
        else:
            _merge(self._parts, self.path)
        self._parts = []
        return self.path


def _merge(parts: list[Path], path: Path) -> None:
    """Parquet files of one table, with columns that differ, as one file with all of them (nulls
    where a part lacks one), in order."""
    schema = pa.unify_schemas([pq.read_schema(p) for p in parts], promote_options="permissive")
    with pq.ParquetWriter(path, schema, compression="zstd") as writer:
        for part in parts:
            for batch in pq.ParquetFile(part).iter_batches():
                columns = [
                    batch.column(f.name).cast(f.type)
                    if f.name in batch.schema.names
                    else pa.nulls(batch.num_rows, f.type)
                    for f in schema
                ]
                writer.write_table(pa.Table.from_arrays(columns, schema=schema))
            part.unlink()


def extract_file(run_id: str, path: Path, size: int, spill_dir: Path | None = None) -> Extractor:
    """The analytics rows of a hot run's file, its first `size` bytes (the recording's chunks)."""
    extractor = Extractor(run_id, spill_dir)
    for event in read_events(path, size):
        if isinstance(event, ArrowMessage) and event.store_id.kind == StoreKind.RECORDING:
            extractor.add(event, chunk_meta(event))
    return extractor


def to_parquet(table: pa.Table) -> bytes:
    out = io.BytesIO()
    pq.write_table(table, out, compression="zstd", row_group_size=1 << 20)
    return out.getvalue()


def partition_key(table: str, robot_id: str, date: str, run_id: str) -> str:
    return f"analytics/{table}/robot_id={robot_id}/date={date}/{run_id}.parquet"


# --- Arrow helpers (the generic ones are services.rrd.values') --------------------------------


def _component(fld: pa.Field) -> str:
    return component_name(fld)
