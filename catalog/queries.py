"""Catalog reads and writes. Services call these with a session from `catalog.db.session_scope`."""

from __future__ import annotations

import datetime as dt
import json
from dataclasses import dataclass, field
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog.models import Robot, Run, RunEntity, RunTimeline


@dataclass
class EntityRecord:
    path: str
    chunks: int
    static_chunks: int
    rows: int
    bytes: int
    archetypes: list[str]
    components: list[str]


@dataclass
class TimelineRecord:
    name: str
    type: str
    min: int
    max: int


@dataclass
class RunRecord:
    """Everything the catalog holds about a run, as the ingest side knows it."""

    id: str
    robot_id: str
    application_id: str
    date: dt.date
    status: str
    tier: str
    started_at: dt.datetime | None
    ended_at: dt.datetime | None
    last_data_at: dt.datetime
    sdk_version: str | None
    chunks: int
    rows: int
    bytes: int
    properties: dict[str, Any]
    entities: list[EntityRecord] = field(default_factory=list)
    timelines: list[TimelineRecord] = field(default_factory=list)


def save_run(session: Session, record: RunRecord, now: dt.datetime) -> None:
    """Insert or update a run with its robot, entities and timelines (replacing the old ones)."""
    robot = session.get(Robot, record.robot_id)
    if robot is None:
        session.add(Robot(id=record.robot_id, created_at=now, last_seen_at=record.last_data_at))
    elif robot.last_seen_at is None or _aware(robot.last_seen_at) < record.last_data_at:
        robot.last_seen_at = record.last_data_at
    run = session.get(Run, record.id)
    if run is None:
        run = Run(id=record.id, created_at=now, pinned=False)
        session.add(run)
    run.robot_id = record.robot_id
    run.application_id = record.application_id
    run.date = record.date
    run.status = record.status
    run.tier = record.tier
    run.started_at = record.started_at
    run.ended_at = record.ended_at
    run.last_data_at = record.last_data_at
    run.sdk_version = record.sdk_version
    run.chunks, run.rows, run.bytes = record.chunks, record.rows, record.bytes
    run.properties = json.dumps(record.properties, sort_keys=True, default=str)
    run.updated_at = now
    session.flush()
    session.execute(sa.delete(RunEntity).where(RunEntity.run_id == record.id))
    session.execute(sa.delete(RunTimeline).where(RunTimeline.run_id == record.id))
    # One multi-row statement each (not one per row): a flush rewrites every live run.
    if record.entities:
        session.execute(sa.insert(RunEntity), [
            {"run_id": record.id, "path": e.path, "chunks": e.chunks, "static_chunks": e.static_chunks,
             "rows": e.rows, "bytes": e.bytes, "archetypes": json.dumps(sorted(e.archetypes)),
             "components": json.dumps(sorted(e.components))} for e in record.entities])
    if record.timelines:
        session.execute(sa.insert(RunTimeline), [
            {"run_id": record.id, "name": t.name, "type": t.type, "min": t.min, "max": t.max}
            for t in record.timelines])


def get_run(session: Session, run_id: str) -> Run | None:
    return session.get(Run, run_id)


def run_entities(session: Session, run_id: str) -> list[RunEntity]:
    return list(session.scalars(sa.select(RunEntity).where(RunEntity.run_id == run_id).order_by(RunEntity.path)))


def run_timelines(session: Session, run_id: str) -> list[RunTimeline]:
    return list(session.scalars(sa.select(RunTimeline).where(RunTimeline.run_id == run_id)
                                .order_by(RunTimeline.name)))


def list_robots(session: Session) -> list[Robot]:
    return list(session.scalars(sa.select(Robot).order_by(Robot.id)))


def _aware(value: dt.datetime) -> dt.datetime:
    """DuckDB hands timestamps back without a zone; they are stored in UTC."""
    return value if value.tzinfo is not None else value.replace(tzinfo=dt.UTC)
