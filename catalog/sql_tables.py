"""The catalog as SQL tables: `robots`, `runs`, `run_entities`, `run_timelines` with all their
columns, and the corpus, `run_metrics`, `events` and `run_tags`, with the columns people query (an
event's range as `start` and `end`; when a metric was computed or a tag added is left out). Their
rows as Arrow tables: what the server hands a SQL worker (which never reaches the catalog), and what
the lakehouse copies."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterable
from typing import Any

import pyarrow as pa
import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.models import Event, Robot, Run, RunEntity, RunMetric, RunTag, RunTimeline

CATALOG_TABLES = {"robots": Robot, "runs": Run, "run_entities": RunEntity, "run_timelines": RunTimeline}

# table -> (column as SQL names it, the catalog's column), in order
CORPUS_TABLES: dict[str, tuple[tuple[str, Any], ...]] = {
    "run_metrics": (
        ("run_id", RunMetric.run_id),
        ("robot_id", RunMetric.robot_id),
        ("name", RunMetric.name),
        ("value", RunMetric.value),
        ("text_value", RunMetric.text_value),
        ("rules_version", RunMetric.rules_version),
    ),
    "events": (
        ("id", Event.id),
        ("run_id", Event.run_id),
        ("robot_id", Event.robot_id),
        ("kind", Event.kind),
        ("severity", Event.severity),
        ("timeline", Event.timeline),
        ("timeline_type", Event.timeline_type),
        ("start", Event.range_start),
        ("end", Event.range_end),
        ("source", Event.source),
        ("origin", Event.origin),
        ("rules_version", Event.rules_version),
        ("label", Event.label),
        ("note", Event.note),
        ("created_at", Event.created_at),
    ),
    "run_tags": (
        ("run_id", RunTag.run_id),
        ("tag", RunTag.tag),
        ("added_by", RunTag.added_by),
    ),
}
SQL_CATALOG_TABLES = (*CATALOG_TABLES, *CORPUS_TABLES)  # every table the server hands a worker


def sql_columns(name: str) -> tuple[tuple[str, Any], ...]:
    """A catalog table's columns as SQL names them: all of a model's, or the corpus tables' choice."""
    if name in CORPUS_TABLES:
        return CORPUS_TABLES[name]
    return tuple((c.name, c) for c in CATALOG_TABLES[name].__table__.columns)


def catalog_tables(
    session: Session, names: Iterable[str] = SQL_CATALOG_TABLES, where: dict[str, Any] | None = None
) -> dict[str, pa.Table]:
    """The catalog as Arrow tables (the same on Postgres and DuckDB): what the SQL views show;
    `where`: a table's condition on its rows, if any."""
    out = {}
    for name in names:
        columns = sql_columns(name)
        query = sa.select(*(column for _, column in columns))
        if where and name in where:
            query = query.where(where[name])
        rows = session.execute(query).all()
        out[name] = pa.table(
            {
                label: pa.array([_plain(row[i]) for row in rows], arrow_type(column.type))
                for i, (label, column) in enumerate(columns)
            }
        )
    return out


def arrow_type(column_type: Any) -> pa.DataType:
    if isinstance(column_type, sa.DateTime):
        return pa.timestamp("us", tz="UTC")
    if isinstance(column_type, sa.Date):
        return pa.date32()
    if isinstance(column_type, sa.Boolean):
        return pa.bool_()
    if isinstance(column_type, sa.Integer):  # BigInteger included
        return pa.int64()
    if isinstance(column_type, sa.Float):  # Double included
        return pa.float64()
    return pa.string()


def _plain(value: Any) -> Any:
    if isinstance(value, dt.datetime) and value.tzinfo is None:
        return value.replace(tzinfo=dt.UTC)  # DuckDB hands back UTC without a zone
    return value
