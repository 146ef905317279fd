"""Catalog reads and writes. Services call these with a session from `catalog.db.session_scope`."""

from __future__ import annotations

import datetime as dt
import json
import uuid
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import pyarrow as pa
import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog import dataset_columns as columns
from catalog import lakehouse
from catalog.db import locks_rows
from catalog.models import (
    Base,
    Dataset,
    JobExecution,
    RetentionEvent,
    Robot,
    Run,
    RunEntity,
    RunLifecycle,
    RunMetric,
    RunObject,
    RunTimeline,
)
from core.clock import aware
from core.errors import NotFoundError
from core.ids import is_id, new_entry_id
from core.states import Tier


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
    status: str  # a RunStatus
    tier: str  # a Tier
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
    elif robot.last_seen_at is None or aware(robot.last_seen_at) < record.last_data_at:
        robot.last_seen_at = record.last_data_at
    run = session.get(Run, record.id, with_for_update=locks_rows(session))  # its columns counted from what it held
    if run is None:
        if record.application_id:  # a new run of the dataset (made with its first run)
            ensure_dataset(session, record.application_id, now).updated_at = now
        run = Run(id=record.id, created_at=now, pinned=False)
        session.add(run)
    elif run.tier != Tier.HOT and record.tier == Tier.HOT:
        # Data for a run already sealed (a late upload): the sealed figures stand until it is
        # sealed again with the new chunks; only its liveliness is news.
        run.status, run.ended_at, run.last_data_at, run.updated_at = (
            record.status,
            record.ended_at,
            max(aware(run.last_data_at), record.last_data_at),
            now,
        )
        return
    held_by = columns.counted_in(run.application_id, run.tier)  # where the run's items were counted
    held_properties = run.properties
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
    run.properties = properties_json(record.properties)
    run.updated_at = now
    session.flush()
    held_entities = session.execute(
        sa.delete(RunEntity).where(RunEntity.run_id == record.id).returning(RunEntity.path, RunEntity.archetypes)
    ).all()
    held_timelines = session.execute(
        sa.delete(RunTimeline).where(RunTimeline.run_id == record.id).returning(RunTimeline.name, RunTimeline.type)
    ).all()
    _recount_columns(session, record, held_by, held_properties, held_entities, held_timelines)
    # One multi-row statement each (not one per row): a flush rewrites every live run.
    if record.entities:
        insert_rows(
            session,
            RunEntity,
            [
                {
                    "run_id": record.id,
                    "path": e.path,
                    "chunks": e.chunks,
                    "static_chunks": e.static_chunks,
                    "rows": e.rows,
                    "bytes": e.bytes,
                    "archetypes": json.dumps(sorted(e.archetypes)),
                    "components": json.dumps(sorted(e.components)),
                }
                for e in record.entities
            ],
        )
    if record.timelines:
        insert_rows(
            session,
            RunTimeline,
            [
                {"run_id": record.id, "name": t.name, "type": t.type, "min": t.min, "max": t.max}
                for t in record.timelines
            ],
        )


def _recount_columns(
    session: Session,
    record: RunRecord,
    held_by: str | None,
    held_properties: str | None,
    held_entities: Sequence[sa.Row[str, str]],
    held_timelines: Sequence[sa.Row[str, str]],
) -> None:
    """Count, in its dataset's columns, what the run holds now and did not, and what it held and
    does not (its metrics are counted where they are written)."""
    now_in = columns.counted_in(record.application_id, record.tier)
    fresh = columns.timeline_items((t.name, t.type) for t in record.timelines)
    fresh |= columns.archetype_items((e.path, e.archetypes) for e in record.entities)
    held = columns.timeline_items((name, kind) for name, kind in held_timelines)
    held |= columns.archetype_items((path, columns.json_names(archetypes)) for path, archetypes in held_entities)
    if held_by != now_in or held_properties != properties_json(record.properties):
        fresh |= columns.property_items(record.properties)
        held |= columns.property_items(columns.json_object(held_properties))
    if held_by != now_in:  # moved to another dataset, or deleted: its metrics move too
        metrics = columns.metric_items(
            session.execute(sa.select(RunMetric.name, RunMetric.text_value).where(RunMetric.run_id == record.id))
        )
        fresh, held = fresh | metrics, held | metrics
    columns.recount(session, (held_by, held), (now_in, fresh))


def insert_rows(session: Session, model: type[Base], rows: list[dict[str, Any]]) -> None:
    """Insert many rows in one statement's worth of work: a flush rewrites every entity of every live
    run. DuckDB's driver runs an executemany row by row (about 0.3 ms a row, BENCHMARKS.md, "Catalog
    flush"), so on DuckDB the rows go in as one Arrow table; Postgres takes the executemany as is."""
    table = model.__table__
    assert isinstance(table, sa.Table)
    if not rows:
        return
    names = list(rows[0])
    types = {c.name: _ARROW_TYPES.get(type(c.type)) for c in table.columns if c.name in names}
    if session.get_bind().dialect.name != "duckdb" or None in types.values():
        session.execute(sa.insert(table), rows)
        return
    try:
        arrow = pa.table({name: pa.array([row[name] for row in rows], type=types[name]) for name in names})
    except (pa.ArrowException, OverflowError, TypeError, ValueError):  # let the database name the problem
        session.execute(sa.insert(table), rows)
        return
    connection = session.connection()
    raw = connection.connection.driver_connection
    assert raw is not None
    listed = ", ".join(f'"{name}"' for name in names)
    raw.register(_ARROW_VIEW, arrow)
    try:  # through SQLAlchemy: its errors, as every other statement's (a full disk is OperationalError)
        connection.exec_driver_sql(f'INSERT INTO "{table.name}" ({listed}) SELECT {listed} FROM {_ARROW_VIEW}')
    finally:
        raw.unregister(_ARROW_VIEW)


_ARROW_VIEW = "fleet_rows_to_insert"  # the connection's, only while one insert_rows runs on it
_ARROW_TYPES: dict[type[Any], pa.DataType] = {
    sa.Integer: pa.int64(),
    sa.BigInteger: pa.int64(),
    sa.String: pa.string(),
    sa.Text: pa.string(),
    sa.Boolean: pa.bool_(),
    sa.Float: pa.float64(),
    sa.LargeBinary: pa.binary(),
}  # (a table with a column of another type is inserted with executemany)


def ensure_dataset(session: Session, name: str, now: dt.datetime, entry_id: str | None = None) -> Dataset:
    """The dataset of application `name`, made if it has none yet (with `entry_id` when a rebuild
    restores the one it had, else a new one)."""
    dataset = session.get(Dataset, name)
    if dataset is None:
        made = entry_id or new_entry_id(name, int(now.timestamp() * 1e9))
        dataset = Dataset(name=name, entry_id=made, created_at=now, updated_at=now)
        session.add(dataset)
        session.flush()
    return dataset


def datasets(session: Session) -> list[Dataset]:
    return list(session.scalars(sa.select(Dataset).order_by(Dataset.name)))


def dataset_entry_id(session: Session, name: str) -> str | None:
    dataset = session.get(Dataset, name)
    return dataset.entry_id if dataset is not None else None


def replace_properties(session: Session, run: Run, properties: dict[str, Any]) -> None:
    """A filed run's properties rewritten (a scrub takes secret fields out): its dataset's columns follow."""
    dataset = columns.counted_in(run.application_id, run.tier)
    held = columns.property_items(columns.json_object(run.properties))
    run.properties = properties_json(properties)
    columns.recount(session, (dataset, held), (dataset, columns.property_items(properties)))
    lakehouse.queue(session, run.id)  # the lakehouse's copy of its row too


def mark_deleted(session: Session, run_id: str, now: dt.datetime) -> bool:
    """Make run `run_id` a tombstone (a deleted run is no segment of its dataset: its columns are
    no longer counted there); False if it already was one (a concurrent delete made it)."""
    dataset, items = columns.run_items(session, run_id)
    changed = session.execute(
        sa.update(Run)
        .where(Run.id == run_id, Run.tier != Tier.DELETED)
        .values(tier=Tier.DELETED, updated_at=now)
        .execution_options(synchronize_session="fetch")
    )
    if not getattr(changed, "rowcount", 0):
        return False
    columns.count(session, dataset, items, -1)
    lakehouse.queue(session, run_id, telemetry=True)  # its rows leave the lakehouse's tables
    return True


def remove_hot_run(session: Session, run_id: str) -> None:
    """Remove a run that never left the hot tier (ingest dropped it), and its robot if it has no
    other run; a sealed run is left alone."""
    run = session.get(Run, run_id)
    if run is None or run.tier != Tier.HOT or session.get(RunLifecycle, run_id) is not None:
        return
    columns.uncount_run(session, run_id)
    session.execute(sa.delete(RunEntity).where(RunEntity.run_id == run_id))
    session.execute(sa.delete(RunTimeline).where(RunTimeline.run_id == run_id))
    robot_id = run.robot_id
    session.delete(run)
    session.flush()
    if session.scalar(sa.select(sa.func.count()).select_from(Run).where(Run.robot_id == robot_id)) == 0:
        session.execute(sa.delete(Robot).where(Robot.id == robot_id))


@dataclass
class ObjectRecord:
    name: str
    key: str
    tier: str  # Tier.WARM or Tier.COLD
    size: int
    sha256: str


def record_promotion(
    session: Session,
    record: RunRecord,
    prefix: str,
    objects: list[ObjectRecord],
    now: dt.datetime,
    detail: str,
    actor: str = "retention",
) -> None:
    """The catalog side of sealing a run into the warm tier, in the caller's transaction; `actor` is
    who asked (a token's subject for `fleet runs promote`, "retention" for the schedule)."""
    save_run(session, record, now)
    life = session.get(RunLifecycle, record.id)
    if life is None:
        session.add(RunLifecycle(run_id=record.id, prefix=prefix, promoted_at=now))
    else:  # sealed again with chunks that came later
        life.prefix, life.promoted_at = prefix, now
    replace_objects(session, record.id, objects)
    add_event(session, record.id, "promote", now, actor, None, detail)


def replace_objects(session: Session, run_id: str, objects: list[ObjectRecord]) -> None:
    _queue_if_analytics_change(session, run_id, [o for o in objects if o.name.startswith(lakehouse.ANALYTICS)])
    session.execute(sa.delete(RunObject).where(RunObject.run_id == run_id))
    if objects:
        session.execute(
            sa.insert(RunObject),
            [
                {"run_id": run_id, "name": o.name, "key": o.key, "tier": o.tier, "size": o.size, "sha256": o.sha256}
                for o in objects
            ],
        )


def add_event(
    session: Session, run_id: str, action: str, now: dt.datetime, actor: str, policy: str | None, detail: str = ""
) -> None:
    lakehouse.queue(session, run_id)  # its tier or pin changed: so does its row in the lakehouse's runs
    session.add(
        RetentionEvent(
            id=uuid.uuid4().hex,
            run_id=run_id,
            action=action,
            occurred_at=now,
            actor=actor,
            policy=policy,
            detail=detail,
        )
    )


def analytics_keys(session: Session, run_id: str) -> set[str]:
    """Keys of the analytics files the catalog holds for a run."""
    return {
        o.key
        for o in session.scalars(
            sa.select(RunObject).where(RunObject.run_id == run_id, RunObject.name.like("analytics/%"))
        )
    }


def replace_analytics(session: Session, run_id: str, objects: list[ObjectRecord]) -> set[str]:
    """Record a run's analytics files (written before it is sealed); returns the keys they replace."""
    old = analytics_keys(session, run_id)
    _queue_if_analytics_change(session, run_id, objects)
    session.execute(sa.delete(RunObject).where(RunObject.run_id == run_id, RunObject.name.like("analytics/%")))
    if objects:
        session.execute(
            sa.insert(RunObject),
            [
                {"run_id": run_id, "name": o.name, "key": o.key, "tier": o.tier, "size": o.size, "sha256": o.sha256}
                for o in objects
            ],
        )
    return old - {o.key for o in objects}


def _queue_if_analytics_change(session: Session, run_id: str, objects: list[ObjectRecord]) -> None:
    """The lakehouse copies a run again when its analytics files change (`catalog.lakehouse`)."""
    held = session.execute(
        sa.select(RunObject.key, RunObject.sha256).where(
            RunObject.run_id == run_id, RunObject.name.like(f"{lakehouse.ANALYTICS}%")
        )
    ).all()
    if {(key, sha) for key, sha in held} != {(o.key, o.sha256) for o in objects}:
        lakehouse.queue(session, run_id, telemetry=True)


def pin_state(session: Session, run_id: str) -> tuple[bool, str | None]:
    """Whether a run is pinned, and by whom: (False, None) for a run the catalog does not have yet."""
    run = session.get(Run, run_id)
    return (bool(run.pinned), run.pinned_by) if run is not None else (False, None)


def run_events(session: Session, run_id: str) -> list[RetentionEvent]:
    return list(
        session.scalars(
            sa.select(RetentionEvent)
            .where(RetentionEvent.run_id == run_id)
            .order_by(RetentionEvent.occurred_at, RetentionEvent.id)
        )
    )


def lifecycle(session: Session, run_id: str) -> RunLifecycle | None:
    return session.get(RunLifecycle, run_id)


def run_and_lifecycle(session: Session, run_id: str) -> tuple[Run, RunLifecycle] | None:
    """A sealed run's row and its lifecycle in one query (what every read of a sealed run asks
    first); None if the run is unknown or was never sealed."""
    if not is_id(run_id):
        return None
    found = session.execute(
        sa.select(Run, RunLifecycle).join(RunLifecycle, RunLifecycle.run_id == Run.id).where(Run.id == run_id)
    ).first()
    return (found[0], found[1]) if found is not None else None


def run_objects(session: Session, run_id: str) -> dict[str, RunObject]:
    return {o.name: o for o in session.scalars(sa.select(RunObject).where(RunObject.run_id == run_id))}


def properties_json(properties: dict[str, Any]) -> str:
    """A run's properties as its row holds them."""
    return json.dumps(properties, sort_keys=True, default=str)


def run_ids_in_tier(session: Session, tier: str) -> list[str]:
    return list(session.scalars(sa.select(Run.id).where(Run.tier == tier).order_by(Run.id)))


def run_end() -> sa.ColumnElement[dt.datetime]:
    """When a run ended, or its last data while it has no end: what retention counts its age from."""
    return sa.func.coalesce(Run.ended_at, Run.last_data_at)


def sealed_runs(
    session: Session, tiers: tuple[str, ...], due: sa.ColumnElement[bool] | None = None
) -> list[tuple[Run, RunLifecycle]]:
    """Runs in the given tiers with their lifecycle rows, oldest end first. With `due`, only the runs
    it holds for and those with a restore asked for or done: what retention's plan may act on, read
    through indexes (Postgres) rather than every sealed run of the fleet."""
    query = sa.select(Run, RunLifecycle).join(RunLifecycle, RunLifecycle.run_id == Run.id).where(Run.tier.in_(tiers))
    if due is not None:
        restoring = sa.select(RunLifecycle.run_id).where(RunLifecycle.restore_state.is_not(None))
        wanted = sa.union(sa.select(Run.id).where(Run.tier.in_(tiers), due), restoring)
        # The ids first, then their rows: Postgres cannot tell how few runs `due` holds for (it
        # assumes the tiers and ends independent, where the warm runs are the newest), and joined in
        # one statement it scans every lifecycle row rather than looking up these few.
        ids = list(session.scalars(wanted.limit(FEW_DUE_RUNS + 1)))
        query = query.where(Run.id.in_(ids if len(ids) <= FEW_DUE_RUNS else wanted))
    return [(run, life) for run, life in session.execute(query.order_by(run_end(), Run.id)).all()]


FEW_DUE_RUNS = 10_000  # more (a policy shortened) are read in one statement


def start_job(session: Session, job: str, node: str, now: dt.datetime) -> str:
    job_id = uuid.uuid4().hex
    session.add(JobExecution(id=job_id, job=job, node=node, started_at=now, outcome="running", detail=""))
    return job_id


def finish_job(session: Session, job_id: str, now: dt.datetime, outcome: str, detail: str) -> None:
    row = session.get(JobExecution, job_id)
    if row is not None:
        row.finished_at, row.outcome, row.detail = now, outcome, detail[:2000]


def prune_jobs(session: Session, before: dt.datetime) -> int:
    """Forget job executions that started before `before`; returns how many."""
    result = session.execute(sa.delete(JobExecution).where(JobExecution.started_at < before))
    return int(getattr(result, "rowcount", 0) or 0)


def recent_jobs(session: Session, limit: int = 20) -> list[JobExecution]:
    return list(session.scalars(sa.select(JobExecution).order_by(JobExecution.started_at.desc()).limit(limit)))


def get_run(session: Session, run_id: str) -> Run | None:
    return session.get(Run, run_id) if is_id(run_id) else None


def get_runs(session: Session, run_ids: Iterable[str]) -> dict[str, Run]:
    """The rows of those of `run_ids` the catalog holds, in one query."""
    wanted = [run_id for run_id in run_ids if is_id(run_id)]
    return {run.id: run for run in session.scalars(sa.select(Run).where(Run.id.in_(wanted)))} if wanted else {}


def run_not_found(run_id: str) -> NotFoundError:
    return NotFoundError(f"no run {run_id!r}: list runs with GET /v1/runs or `fleet runs ls`")


def require_run(session: Session, run_id: str) -> Run:
    """The run, or a 404 naming it and how to list runs."""
    run = get_run(session, run_id)
    if run is None:
        raise run_not_found(run_id)
    return run


def run_record(session: Session, run_id: str) -> RunRecord | None:
    """A run as its catalog rows hold it (what `save_run` wrote), None if the catalog lacks it."""
    run = session.get(Run, run_id)
    if run is None:
        return None
    return RunRecord(
        id=run.id,
        robot_id=run.robot_id,
        application_id=run.application_id,
        date=run.date,
        status=run.status,
        tier=run.tier,
        started_at=_aware_or_none(run.started_at),
        ended_at=_aware_or_none(run.ended_at),
        last_data_at=aware(run.last_data_at),
        sdk_version=run.sdk_version,
        chunks=run.chunks,
        rows=run.rows,
        bytes=run.bytes,
        properties=json.loads(run.properties),
        entities=[
            EntityRecord(
                e.path, e.chunks, e.static_chunks, e.rows, e.bytes, json.loads(e.archetypes), json.loads(e.components)
            )
            for e in run_entities(session, run_id)
        ],
        timelines=[TimelineRecord(t.name, t.type, t.min, t.max) for t in run_timelines(session, run_id)],
    )


def _aware_or_none(value: dt.datetime | None) -> dt.datetime | None:
    return aware(value) if value is not None else None


def run_entities(session: Session, run_id: str) -> list[RunEntity]:
    return list(session.scalars(sa.select(RunEntity).where(RunEntity.run_id == run_id).order_by(RunEntity.path)))


def run_timelines(session: Session, run_id: str) -> list[RunTimeline]:
    return list(session.scalars(sa.select(RunTimeline).where(RunTimeline.run_id == run_id).order_by(RunTimeline.name)))


def timeline_types(session: Session, run_ids: set[str]) -> dict[tuple[str, str], str]:
    """(run id, timeline) -> its type (sequence, timestamp, duration), for a few runs (a page's)."""
    query = sa.select(RunTimeline.run_id, RunTimeline.name, RunTimeline.type).where(
        RunTimeline.run_id.in_(sorted(run_ids))
    )
    return {(run_id, name): kind for run_id, name, kind in session.execute(query).all()}


def list_robots(session: Session) -> list[Robot]:
    return list(session.scalars(sa.select(Robot).order_by(Robot.id)))
