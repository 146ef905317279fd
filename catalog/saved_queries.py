"""Catalog reads and writes of saved queries: SQL with a unique name and the chart it is drawn as."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.models import SavedQuery
from core.clock import aware, iso_utc
from core.errors import AlreadyExistsError, NotFoundError

CHARTS = ("line", "bar", "table")


class NameTakenError(AlreadyExistsError):
    """Another saved query has this name (names are unique: they are the dashboards' titles)."""


@dataclass(frozen=True)
class SavedQueryRecord:
    id: str
    name: str
    sql: str
    chart: str  # one of CHARTS
    created_by: str
    created_at: dt.datetime
    updated_at: dt.datetime

    def to_dict(self) -> dict[str, str | None]:
        return {
            "id": self.id,
            "name": self.name,
            "sql": self.sql,
            "chart": self.chart,
            "created_by": self.created_by,
            "created_at": iso_utc(self.created_at),
            "updated_at": iso_utc(self.updated_at),
        }


def name_taken(name: str) -> NameTakenError:
    return NameTakenError(f"a saved query is already named {name!r}: choose another name, or delete that one first")


def add_query(session: Session, record: SavedQueryRecord) -> SavedQueryRecord:
    """Add `record`; ALREADY_EXISTS if its name is taken (also when another writer took it at the
    same moment: Postgres's unique index refuses the second)."""
    if session.scalar(sa.select(SavedQuery.id).where(SavedQuery.name == record.name)) is not None:
        raise name_taken(record.name)
    session.add(
        SavedQuery(
            id=record.id,
            name=record.name,
            sql=record.sql,
            chart=record.chart,
            created_by=record.created_by,
            created_at=record.created_at,
            updated_at=record.updated_at,
        )
    )
    try:
        session.flush()
    except sa.exc.IntegrityError as exc:
        raise name_taken(record.name) from exc
    return record


def saved_query(session: Session, query_id: str) -> SavedQueryRecord | None:
    row = session.get(SavedQuery, query_id)
    return _record(row) if row is not None else None


def saved_queries(session: Session) -> list[SavedQueryRecord]:
    """Every saved query, by name."""
    return [_record(row) for row in session.scalars(sa.select(SavedQuery).order_by(SavedQuery.name, SavedQuery.id))]


def delete_query(session: Session, query_id: str) -> SavedQueryRecord:
    """Delete a saved query; NOT_FOUND if there is none with this id."""
    row = session.get(SavedQuery, query_id)
    if row is None:
        raise query_not_found(query_id)
    record = _record(row)
    session.delete(row)
    session.flush()
    return record


def query_not_found(query_id: str) -> NotFoundError:
    return NotFoundError(f"no saved query {query_id!r}: it may have been deleted (list them: GET /v1/queries)")


def _record(row: SavedQuery) -> SavedQueryRecord:
    return SavedQueryRecord(
        row.id,
        row.name,
        row.sql,
        row.chart,
        row.created_by,
        aware(row.created_at),
        aware(row.updated_at),
    )
