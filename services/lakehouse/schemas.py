"""The lakehouse tables' Iceberg schemas, and a run's analytics rows made to fit them.

Iceberg format version 2, which every engine reads, holds timestamps to the microsecond: each table
keeps `log_time` as a timestamp (microseconds, what engines filter and partition on) and its exact
value as `log_time_ns`. A run's other timelines become columns as they appear (schema evolution):
sequences and durations as `long` (durations in nanoseconds), timestamps to the microsecond.
Partitioned by robot and date (identity transforms): a reader filtering on them reads only those
files, without naming a partition. Field ids are fixed here, so every node makes the same tables.
"""

from __future__ import annotations

import datetime as dt

import pyarrow as pa
import pyarrow.compute as pc
from pyiceberg.partitioning import PartitionField, PartitionSpec
from pyiceberg.schema import Schema
from pyiceberg.transforms import IdentityTransform
from pyiceberg.types import (
    BooleanType,
    DateType,
    DoubleType,
    IcebergType,
    IntegerType,
    LongType,
    NestedField,
    StringType,
    TimestampType,
    TimestamptzType,
)

from catalog.sql_tables import arrow_type, sql_columns

NAMESPACE = "fleet"
TELEMETRY = ("scalars", "text_logs", "transforms")
# The catalog's tables a run has rows in, as the depot's SQL shows them (`catalog.sql_tables`), with
# the column naming the run and the columns each is partitioned by.
CATALOG = ("runs", "run_metrics", "events", "run_tags")
RUN_COLUMN = {"runs": "id", "run_metrics": "run_id", "events": "run_id", "run_tags": "run_id"}
_CATALOG_PARTITIONS = {"runs": ("robot_id", "date"), "run_metrics": ("robot_id",), "events": ("robot_id",)}
TABLES = TELEMETRY + CATALOG
LOG_TIME = "log_time"
LOG_TIME_NS = "log_time_ns"
# A fleet's timelines are few; past this many columns a table takes no new timeline (its rows keep
# their log_time), so a robot naming a timeline per run cannot grow the schema without bound.
MAX_COLUMNS = 200

_HEAD: tuple[tuple[str, IcebergType], ...] = (
    ("run_id", StringType()),
    ("robot_id", StringType()),
    ("date", DateType()),
    ("entity", StringType()),
)
_TAIL: tuple[tuple[str, IcebergType], ...] = ((LOG_TIME, TimestampType()), (LOG_TIME_NS, LongType()))
_VALUES: dict[str, tuple[tuple[str, IcebergType], ...]] = {
    "scalars": (("component", StringType()), ("instance", IntegerType()), ("value", DoubleType())),
    "text_logs": (("level", StringType()), ("text", StringType())),
    "transforms": tuple((name, DoubleType()) for name in ("tx", "ty", "tz", "qx", "qy", "qz", "qw")),
}


def fixed_columns(table: str) -> tuple[str, ...]:
    return tuple(name for name, _ in _fields(table))


def _fields(table: str) -> tuple[tuple[str, IcebergType], ...]:
    if table in TELEMETRY:
        return (*_HEAD, *_VALUES[table], *_TAIL)
    return tuple((label, _ICEBERG[str(arrow_type(column.type))]) for label, column in sql_columns(table))


_ICEBERG: dict[str, IcebergType] = {
    "string": StringType(),
    "int64": LongType(),
    "double": DoubleType(),
    "bool": BooleanType(),
    "date32[day]": DateType(),
    "timestamp[us, tz=UTC]": TimestamptzType(),
}


def schema(table: str) -> Schema:
    """The table's schema as created (timeline columns are added to telemetry tables as runs bring
    them; a catalog table gains the columns a catalog migration adds)."""
    return Schema(
        *(NestedField(i, name, kind, required=False) for i, (name, kind) in enumerate(_fields(table), start=1)),
    )


def partition_spec(table: str) -> PartitionSpec:
    ids = {name: i for i, name in enumerate(fixed_columns(table), start=1)}
    by = ("robot_id", "date") if table in TELEMETRY else _CATALOG_PARTITIONS.get(table, ())
    return PartitionSpec(
        *(PartitionField(ids[name], 1000 + i, IdentityTransform(), name) for i, name in enumerate(by)),
    )


def iceberg_rows(table: str, batch: pa.RecordBatch, robot_id: str, date: dt.date) -> pa.Table:
    """A batch of a run's analytics file (`services.analytics.extract`: its fixed columns, `log_time`
    and one column per other timeline) as rows of the Iceberg table: with the robot and date its
    file's partition held, times in types Iceberg has, in the table's column order."""
    n = batch.num_rows
    out: dict[str, pa.Array] = {
        "robot_id": pa.array([robot_id] * n, pa.string()),
        "date": pa.array([date] * n, pa.date32()),
    }
    fixed = set(fixed_columns(table))
    extracted = fixed - {"robot_id", "date", LOG_TIME, LOG_TIME_NS}  # the file's own fixed columns
    timelines = {}
    for name, column in zip(batch.schema.names, batch.columns, strict=True):
        if name == LOG_TIME:
            exact = _nanoseconds(column)
            out[LOG_TIME] = pc.cast(exact, pa.timestamp("us"), safe=False) if exact is not None else column
            out[LOG_TIME_NS] = exact.view(pa.int64()) if exact is not None else pa.nulls(n, pa.int64())
        elif name in extracted:
            out[name] = column
        else:  # a timeline: `timeline_NAME` where a column of the table has its name (as extraction does)
            timelines[name if name not in fixed else f"timeline_{name}"] = _timeline(column)
    if LOG_TIME not in out:  # a run without log_time: every file has both columns, null here
        out[LOG_TIME] = pa.nulls(n, pa.timestamp("us"))
        out[LOG_TIME_NS] = pa.nulls(n, pa.int64())
    out.update(timelines)
    order = [c for c in fixed_columns(table) if c in out] + [c for c in out if c not in fixed]
    return pa.table({c: out[c] for c in order})


def _nanoseconds(column: pa.Array) -> pa.Array | None:
    if not pa.types.is_timestamp(column.type):
        return None
    return pc.cast(column, pa.timestamp("ns")) if column.type.unit != "ns" or column.type.tz else column


def _timeline(column: pa.Array) -> pa.Array:
    kind = column.type
    if pa.types.is_timestamp(kind):
        return pc.cast(column, pa.timestamp("us", kind.tz), safe=False)
    if pa.types.is_duration(kind):
        return pc.cast(column, pa.duration("ns")).view(pa.int64())
    if pa.types.is_integer(kind):
        return pc.cast(column, pa.int64())
    return column
