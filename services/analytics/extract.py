"""Analytics tables extracted from a run's chunks: scalars, text logs and transforms, as Parquet.

One pass over the chunks (the same pass that seals the run); only chunks holding one of these
archetypes are decoded. Every table has `run_id`, `entity`, `log_time` and one column per other
timeline of the run (named after it; `timeline_NAME` if the name is taken). Robot and date are
not stored in the files: they are the Hive partition (`robot_id=R/date=D/`) the file lies in.
"""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field
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


@dataclass
class Extractor:
    """Collects the analytics rows of one run, chunk by chunk."""

    run_id: str
    batches: dict[str, list[pa.Table]] = field(default_factory=lambda: {t: [] for t in TABLES})

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
        self.batches[table].append(pa.table(columns))

    def tables(self) -> dict[str, pa.Table]:
        """Each non-empty table, its per-chunk pieces unified (runs may add timelines as they go)."""
        return {
            name: pa.concat_tables(parts, promote_options="permissive") for name, parts in self.batches.items() if parts
        }


def extract_file(run_id: str, path: Path, size: int) -> Extractor:
    """The analytics rows of a hot run's file, its first `size` bytes (the recording's chunks)."""
    extractor = Extractor(run_id)
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
