"""What a dataset's runs hold that its segment table makes columns of, counted as runs are
written: the table's schema is then one indexed read, not a read of every run of the dataset (at a
million runs that read took 16-24 s before the first row went out, BENCHMARKS.md).

An item is a recording property's component with a kind of value, an archetype logged on a property
entity, a timeline with its type, or a metric as a number or as text. Each is counted once per run
of the dataset that holds it and is not deleted: a writer compares the run's items before and after
its own write and adds or takes away the difference; concurrent writers add with an upsert.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.dialects.postgresql import insert
from sqlalchemy.orm import Session

from catalog.db import locks_rows
from catalog.models import DatasetColumn, Run, RunEntity, RunMetric, RunTimeline
from core.states import Tier

PROPERTY, ARCHETYPE, TIMELINE, METRIC = "property", "archetype", "timeline", "metric"
# Rerun's property entity (`rr.send_property` logs under it); services.rrd.manifest.PROPERTIES_ENTITY.
PROPERTIES_ENTITY = "/__properties"
NONFINITE = frozenset({"NaN", "Infinity", "-Infinity"})  # how the catalog writes non-finite floats

Item = tuple[str, str, str]  # (kind, name, detail)


def value_kind(item: Any) -> str:
    """The kind of one property value, as the segment table types its column."""
    if isinstance(item, bool):
        return "bool"
    if isinstance(item, int):
        return "int"
    if isinstance(item, float):
        return "float"
    if isinstance(item, str):
        return "nonfinite" if item in NONFINITE else "str"
    return "other"  # structs and nested lists: shown as JSON text


def property_values(value: Any) -> list[Any] | None:
    """A property's values as a list: the catalog keeps a one-value property as the value."""
    if value is None:
        return None
    return value if isinstance(value, list) else [value]


def property_name(prop: str, component: str) -> str:
    return json.dumps([prop, component])


def property_key(name: str) -> tuple[str, str]:
    """(property, component) of a property item's name."""
    prop, component = json.loads(name)
    return str(prop), str(component)


def property_items(properties: dict[str, Any]) -> set[Item]:
    found: set[Item] = set()
    for prop, values in properties.items():
        if not isinstance(values, dict):
            continue
        for component, value in values.items():
            name = property_name(prop, str(component))
            found.update((PROPERTY, name, value_kind(item)) for item in property_values(value) or ())
            if not property_values(value):  # a column still, of no kind yet
                found.add((PROPERTY, name, ""))
    return found


def is_property_entity(path: str) -> bool:
    return path == PROPERTIES_ENTITY or path.startswith(PROPERTIES_ENTITY + "/")


def archetype_items(entities: Iterable[tuple[str, Iterable[str]]]) -> set[Item]:
    """(path, archetypes) of a run's entities: those of its property entities."""
    return {(ARCHETYPE, path, archetype) for path, names in entities if is_property_entity(path) for archetype in names}


def timeline_items(timelines: Iterable[tuple[str, str]]) -> set[Item]:
    return {(TIMELINE, name, kind) for name, kind in timelines}


def metric_items(metrics: Iterable[tuple[str, str | None]]) -> set[Item]:
    """(name, text value) of a run's metrics."""
    return {(METRIC, name, "number" if text is None else "text") for name, text in metrics}


MAX_NAME = 1000  # characters: a longer property or entity name is no column (an index key holds ~2,700 bytes)
PENDING = "fleet.dataset_column_changes"  # the session's changes to the counts, applied as it commits


def count(session: Session, application_id: str | None, items: set[Item], step: int) -> None:
    """`step` (1 or -1) more runs of `application_id` hold each of `items`: applied to the counts
    when the session commits (`apply_pending`), all of a transaction's together in one order, so two
    nodes' transactions never hold each other's count rows crosswise."""
    if not application_id or not items:
        return
    pending: dict[tuple[str, str, str, str], int] = session.info.setdefault(PENDING, {})
    for kind, name, detail in items:
        if indexable((kind, name, detail)):
            key = (application_id, kind, name, detail)
            pending[key] = pending.get(key, 0) + step


def indexable(item: Item) -> bool:
    return len(item[1]) <= MAX_NAME and len(item[2]) <= MAX_NAME


@event.listens_for(Session, "before_commit")
def apply_pending(session: Session) -> None:
    """Apply the session's changes to the counts: what is added in one upsert, then what is taken
    away, each in the order of its keys."""
    pending: dict[tuple[str, str, str, str], int] = session.info.pop(PENDING, {})
    added = [(key, n) for key, n in sorted(pending.items()) if n > 0]
    if added:
        rows = [
            {"application_id": app, "kind": kind, "name": name, "detail": detail, "runs": n}
            for (app, kind, name, detail), n in added
        ]
        statement = insert(DatasetColumn).values(rows)
        session.execute(
            statement.on_conflict_do_update(
                index_elements=["application_id", "kind", "name", "detail"],
                set_={"runs": DatasetColumn.runs + statement.excluded.runs},
            )
        )
    for (app, kind, name, detail), n in sorted(pending.items()):
        if n < 0:
            key = sa.and_(
                DatasetColumn.application_id == app,
                DatasetColumn.kind == kind,
                DatasetColumn.name == name,
                DatasetColumn.detail == detail,
            )
            session.execute(sa.update(DatasetColumn).where(key).values(runs=DatasetColumn.runs + n))
            session.execute(sa.delete(DatasetColumn).where(key, DatasetColumn.runs <= 0))


@event.listens_for(Session, "after_rollback")
def _forget_pending(session: Session) -> None:
    session.info.pop(PENDING, None)


def recount(session: Session, before: tuple[str | None, set[Item]], after: tuple[str | None, set[Item]]) -> None:
    """A run's items were `before` (its dataset, or None where it was not counted: deleted) and are
    `after`: count the difference."""
    (held_by, held), (now_in, fresh) = before, after
    if held_by == now_in:
        count(session, now_in, fresh - held, 1)
        count(session, held_by, held - fresh, -1)
        return
    count(session, held_by, held, -1)
    count(session, now_in, fresh, 1)


def counted_in(application_id: str | None, tier: str | None) -> str | None:
    """The dataset a run is counted in: none for a deleted run (a tombstone is no segment)."""
    return application_id if tier != Tier.DELETED else None


def run_items(session: Session, run_id: str) -> tuple[str | None, set[Item]]:
    """The dataset run `run_id` is counted in, and the items it holds, read from the catalog."""
    query = sa.select(Run.application_id, Run.tier, Run.properties).where(Run.id == run_id)
    # its row locked first on Postgres: a concurrent writer of the run waits until this one commits
    run = session.execute(query.with_for_update() if locks_rows(session) else query).first()
    if run is None:
        return None, set()
    # each read whole before the next statement: DuckDB drops a result the connection has not read
    entities = session.execute(sa.select(RunEntity.path, RunEntity.archetypes).where(RunEntity.run_id == run_id)).all()
    timelines = session.execute(sa.select(RunTimeline.name, RunTimeline.type).where(RunTimeline.run_id == run_id)).all()
    metrics = session.execute(sa.select(RunMetric.name, RunMetric.text_value).where(RunMetric.run_id == run_id)).all()
    items = property_items(json_object(run.properties))
    items |= archetype_items((path, json_names(archetypes)) for path, archetypes in entities)
    items |= timeline_items((name, kind) for name, kind in timelines)
    items |= metric_items((name, text) for name, text in metrics)
    return counted_in(run.application_id, run.tier), items


def uncount_run(session: Session, run_id: str) -> None:
    """Run `run_id` is being deleted (or removed): its items are no longer its dataset's."""
    application_id, items = run_items(session, run_id)
    count(session, application_id, items, -1)


def recount_metrics(session: Session, run_id: str, before: set[Item], after: set[Item]) -> None:
    """A run's metrics were replaced: count the difference in its dataset."""
    if before != after:
        query = sa.select(Run.application_id, Run.tier).where(Run.id == run_id)
        run = session.execute(query.with_for_update() if locks_rows(session) else query).first()
        if run is not None:
            dataset = counted_in(run.application_id, run.tier)
            recount(session, (dataset, before), (dataset, after))


@dataclass
class DatasetColumns:
    """What the runs of one dataset have held."""

    properties: dict[tuple[str, str], set[str]] = field(default_factory=dict)  # (property, component) -> kinds
    archetypes: dict[str, set[str]] = field(default_factory=dict)  # property entity -> archetypes
    timelines: dict[str, str] = field(default_factory=dict)  # timeline -> the type most runs log it with
    metrics: dict[str, bool] = field(default_factory=dict)  # metric -> whether any run holds it as text


def dataset_columns(session: Session, application_id: str) -> DatasetColumns:
    apply_pending(session)  # what this transaction changed, read back in it
    found = DatasetColumns()
    best: dict[str, tuple[int, str]] = {}
    query = sa.select(DatasetColumn.kind, DatasetColumn.name, DatasetColumn.detail, DatasetColumn.runs).where(
        DatasetColumn.application_id == application_id, DatasetColumn.runs > 0
    )
    for kind, name, detail, runs in session.execute(query):
        if kind == PROPERTY:
            kinds = found.properties.setdefault(property_key(name), set())
            if detail:
                kinds.add(detail)
        elif kind == ARCHETYPE:
            found.archetypes.setdefault(name, set()).add(detail)
        elif kind == TIMELINE and (name not in best or (runs, detail) > best[name]):
            best[name] = (runs, detail)
        elif kind == METRIC:
            found.metrics[name] = found.metrics.get(name, False) or detail == "text"
    found.timelines = {name: detail for name, (_, detail) in best.items()}
    return found


def refill(session: Session, page: int = 10_000) -> int:
    """Count every run's items again from the runs themselves (a catalog filled some other way
    than by its writers: an upgrade, a bulk load, `fleet db recount`); the runs read (deleted ones
    are not)."""
    session.info.pop(PENDING, None)
    session.execute(sa.delete(DatasetColumn))
    counts: dict[tuple[str, Item], int] = {}

    def add(application_id: str | None, items: set[Item]) -> None:
        for item in items:
            if application_id and indexable(item):
                counts[(application_id, item)] = counts.get((application_id, item), 0) + 1

    counted = Run.tier != Tier.DELETED
    read, after = 0, ""
    while True:
        batch = session.execute(
            sa.select(Run.id, Run.application_id, Run.properties)
            .where(Run.id > after, counted)
            .order_by(Run.id)
            .limit(page)
        ).all()
        if not batch:
            break
        for _, application_id, text in batch:
            add(application_id, property_items(json_object(text)))
        read, after = read + len(batch), batch[-1][0]
    grouped = [
        (
            TIMELINE,
            sa.select(Run.application_id, RunTimeline.name, RunTimeline.type, sa.func.count())
            .join(Run, Run.id == RunTimeline.run_id)
            .where(counted)
            .group_by(Run.application_id, RunTimeline.name, RunTimeline.type),
        ),
        (
            METRIC,
            sa.select(Run.application_id, RunMetric.name, RunMetric.text_value.is_(None), sa.func.count())
            .join(Run, Run.id == RunMetric.run_id)
            .where(counted)
            .group_by(Run.application_id, RunMetric.name, RunMetric.text_value.is_(None)),
        ),
    ]
    for kind, query in grouped:
        for application_id, name, detail, runs in session.execute(query):
            if application_id and len(name) <= MAX_NAME:
                shown = ("number" if detail else "text") if kind == METRIC else str(detail)
                counts[(application_id, (kind, name, shown))] = (
                    counts.get((application_id, (kind, name, shown)), 0) + runs
                )
    entities = sa.select(Run.application_id, RunEntity.path, RunEntity.archetypes).join(Run, Run.id == RunEntity.run_id)
    entities = entities.where(counted, RunEntity.path.startswith(PROPERTIES_ENTITY, autoescape=True))
    for application_id, path, archetypes in session.execute(entities):
        add(application_id, archetype_items([(path, json_names(archetypes))]))
    rows = [
        {"application_id": app, "kind": kind, "name": name, "detail": detail, "runs": runs}
        for (app, (kind, name, detail)), runs in sorted(counts.items())
    ]
    for start in range(0, len(rows), page):
        session.execute(sa.insert(DatasetColumn), rows[start : start + page])
    return read


def json_object(text: str | None) -> dict[str, Any]:
    try:
        found = json.loads(text or "{}")
    except ValueError:
        return {}
    return found if isinstance(found, dict) else {}


def json_names(text: str | None) -> list[str]:
    try:
        listed = json.loads(text or "[]")
    except ValueError:
        return []
    return [name for name in listed if isinstance(name, str)] if isinstance(listed, list) else []
