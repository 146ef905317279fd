"""Finding runs: robots, runs with filters, sort and an opaque cursor, and one run in detail, each as
the JSON the REST API answers."""

from __future__ import annotations

import base64
import datetime as dt
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import sqlalchemy as sa
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import Session, sessionmaker

from catalog import edge as edge_queries
from catalog import nodes, queries
from catalog.db import session_scope
from catalog.models import Robot, Run, RunEntity
from core.clock import iso_utc
from core.errors import BadParameterError, NotFoundError
from core.states import RunStatus, Tier
from services.policies import Policies
from services.runs import corpus_filters
from services.runs.corpus_answer import corpus_answer
from services.runs.corpus_filters import MetricCondition

if TYPE_CHECKING:
    from services.ingest.service import IngestService

# A run as ingest knows it now, if it is hot on this node (None: not hot here).
HotLookup = Callable[[str], "queries.RunRecord | None"]

MAX_LIMIT = 1000
MAX_ENTITY_FILTERS = 32  # each is a subquery: a bounded number keeps the query plannable
MAX_PROPERTY_FILTERS = 32
MAX_CORPUS_FILTERS = 32  # of each of metric, tag, event
MAX_CURSOR_LENGTH = 2048  # a cursor this service gives out is a few dozen characters
SORTS = ("-started_at", "started_at", "-bytes", "bytes", "id", "-id")
SORT_FORMS = (*SORTS, "metric.NAME", "-metric.NAME")
STATUSES = tuple(RunStatus)
TIERS = tuple(Tier)


@dataclass
class RunFilter:
    robot: list[str] = field(default_factory=list)
    application: list[str] = field(default_factory=list)
    since: dt.datetime | None = None
    until: dt.datetime | None = None
    status: str | None = None
    tier: str | None = None
    entity: list[str] = field(default_factory=list)  # `/world/**` (subtree) or an exact path
    properties: dict[str, str] = field(default_factory=dict)  # "fleet.robot_id" -> value
    metric: list[str] = field(default_factory=list)  # `distance_m>100` (corpus_filters.MetricCondition)
    tag: list[str] = field(default_factory=list)  # has every one of these tags
    event: list[str] = field(default_factory=list)  # has at least one event of each of these kinds
    sort: str = "-started_at"
    limit: int = 100
    cursor: str | None = None

    def check(self) -> list[MetricCondition]:
        """Refuse what cannot be asked (a 422 naming the parameter); the metric conditions parsed."""
        if self.sort not in SORTS and corpus_filters.sort_metric(self.sort) is None:
            raise BadParameterError("sort", f"{self.sort!r} is not one of {', '.join(SORT_FORMS)}")
        if not 1 <= self.limit <= MAX_LIMIT:
            raise BadParameterError("limit", f"{self.limit} is not between 1 and {MAX_LIMIT}")
        if self.status is not None and self.status not in STATUSES:
            raise BadParameterError("status", f"{self.status!r} is not one of {', '.join(STATUSES)}")
        if self.tier is not None and self.tier not in TIERS:
            raise BadParameterError("tier", f"{self.tier!r} is not one of {', '.join(TIERS)}")
        for name, count, most in (
            ("entity", len(self.entity), MAX_ENTITY_FILTERS),
            ("property", len(self.properties), MAX_PROPERTY_FILTERS),
            ("metric", len(self.metric), MAX_CORPUS_FILTERS),
            ("tag", len(self.tag), MAX_CORPUS_FILTERS),
            ("event", len(self.event), MAX_CORPUS_FILTERS),
        ):
            if count > most:
                raise BadParameterError(name, f"{count} filters: at most {most}")
        for key in self.properties:
            if key.count(".") != 1 or not all(key.split(".")):
                raise BadParameterError("property", f"{key!r} is not NAME.FIELD=VALUE (e.g. fleet.robot_id=robot-7)")
        texts = (
            ("robot", self.robot),
            ("application", self.application),
            ("entity", self.entity),
            ("property", [*self.properties, *self.properties.values()]),
            ("metric", self.metric),
            ("tag", self.tag),
            ("event", self.event),
        )
        for name, values in texts:
            if any("\x00" in value for value in values):
                raise BadParameterError(name, "contains a NUL character, which no run id, path or property holds")
        return [MetricCondition.parse(expression) for expression in self.metric]


def parse_time(name: str, text: str | None) -> dt.datetime | None:
    """ISO-8601 (a date, or a date and time; UTC when no zone is given)."""
    if text is None:
        return None
    try:
        value = dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise BadParameterError(name, f"{text!r} is not ISO-8601, e.g. 2026-11-21 or 2026-11-21T08:00:00Z") from None
    return value if value.tzinfo is not None else value.replace(tzinfo=dt.UTC)


def parse_properties(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise BadParameterError("property", f"{item!r} is not NAME.FIELD=VALUE (e.g. fleet.robot_id=robot-7)")
        out[key] = value
    return out


def _entity_condition(pattern: str) -> sa.ColumnElement[bool]:
    if pattern.endswith("/**"):
        root = pattern[:-3].rstrip("/")
        prefix = (root + "/").replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        return sa.or_(RunEntity.path == (root or "/"), RunEntity.path.like(prefix + "%", escape="\\"))
    return RunEntity.path == pattern


def _property_value(session: Session, name: str, field_name: str) -> sa.ColumnElement[Any]:
    if session.get_bind().dialect.name == "postgresql":
        return sa.func.jsonb_extract_path_text(sa.cast(Run.properties, JSONB), name, field_name)
    # a JSON pointer (RFC 6901: `~` and `/` escaped) takes any key as is, quotes included
    pointer = "".join("/" + part.replace("~", "~0").replace("/", "~1") for part in (name, field_name))
    return sa.func.json_extract_string(Run.properties, pointer)


def _sort_key(sort: str) -> sa.ColumnElement[Any]:
    column = sort.lstrip("-")
    if column == "started_at":
        return sa.func.coalesce(Run.started_at, Run.created_at)
    return getattr(Run, column)  # type: ignore[no-any-return]


def _encode_cursor(value: Any, run_id: str) -> str:
    if isinstance(value, dt.datetime):
        value = (value if value.tzinfo else value.replace(tzinfo=dt.UTC)).isoformat()
    return base64.urlsafe_b64encode(json.dumps([value, run_id]).encode()).decode().rstrip("=")


def _decode_cursor(cursor: str, sort: str) -> tuple[Any, str]:
    """The sort value and run id a cursor carries, checked against the sort's type (a cursor is
    client input: a tampered one is a 422, never a query error)."""
    bad = BadParameterError(
        "cursor", "not a cursor this service gave out for this sort: pass `next_cursor` as is, with the same sort"
    )
    if len(cursor) > MAX_CURSOR_LENGTH:
        raise bad
    try:
        decoded = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
    except (ValueError, TypeError, RecursionError):
        raise bad from None
    if not (isinstance(decoded, list) and len(decoded) == 2 and isinstance(decoded[1], str)):
        raise bad
    value, run_id = decoded
    column = sort.lstrip("-")
    if corpus_filters.sort_metric(sort) is not None:
        try:
            value = corpus_filters.cursor_value(value)
        except ValueError:
            raise bad from None
    elif column == "started_at":
        try:
            value = dt.datetime.fromisoformat(value) if isinstance(value, str) else None
        except ValueError:
            value = None
        if value is None:
            raise bad
        value = value if value.tzinfo is not None else value.replace(tzinfo=dt.UTC)
    elif column == "bytes":
        if type(value) is not int or not -(2**63) <= value < 2**63:
            raise bad
    elif not isinstance(value, str):
        raise bad
    if "\x00" in run_id or (isinstance(value, str) and "\x00" in value):
        raise bad
    return value, run_id


def list_runs(session: Session, flt: RunFilter) -> tuple[list[Run], str | None]:
    """A page of runs and the cursor of the next page (None at the end)."""
    metric_conditions = flt.check()
    query = sa.select(Run).where(Run.tier != Tier.DELETED) if flt.tier is None else sa.select(Run)
    if flt.robot:
        query = query.where(Run.robot_id.in_(flt.robot))
    if flt.application:
        query = query.where(Run.application_id.in_(flt.application))
    started = sa.func.coalesce(Run.started_at, Run.created_at)
    if flt.since is not None:
        query = query.where(started >= flt.since)
    if flt.until is not None:
        query = query.where(started < flt.until)
    if flt.status is not None:
        query = query.where(Run.status == flt.status)
    if flt.tier is not None:
        query = query.where(Run.tier == flt.tier)
    for pattern in flt.entity:
        query = query.where(sa.exists().where(RunEntity.run_id == Run.id, _entity_condition(pattern)))
    for prop, value in flt.properties.items():
        name, field_name = prop.split(".")
        query = query.where(_property_value(session, name, field_name) == value)
    for condition in metric_conditions:
        query = query.where(condition.condition())
    for tag in flt.tag:
        query = query.where(corpus_filters.tag_condition(tag))
    for kind in flt.event:
        query = query.where(corpus_filters.event_condition(kind))
    rows = _page(session, query, flt)
    runs = [row[0] for row in rows[: flt.limit]]
    next_cursor = None
    if len(rows) > flt.limit:
        last = rows[flt.limit - 1]
        next_cursor = _encode_cursor(last[1], last[0].id)
    return runs, next_cursor


def _page(session: Session, query: sa.Select[Any], flt: RunFilter) -> list[tuple[Run, Any]]:
    """Up to `flt.limit` + 1 runs of `query` from the cursor on in the filter's sort, each with its
    sort key (what the next cursor carries)."""
    descending = flt.sort.startswith("-")
    sorted_metric = corpus_filters.sort_metric(flt.sort)
    if sorted_metric is not None:  # nulls (runs without the metric) last, either way
        after = _decode_cursor(flt.cursor, flt.sort) if flt.cursor else None
        return corpus_filters.metric_sorted(session, query, sorted_metric, descending, after, flt.limit + 1)
    key = _sort_key(flt.sort)
    if flt.cursor:
        last_value, last_id = _decode_cursor(flt.cursor, flt.sort)
        # The first condition bounds the index range (the key is never null); the second is exact.
        if descending:
            query = query.where(
                key <= last_value, sa.or_(key < last_value, sa.and_(key == last_value, Run.id < last_id))
            )
        else:
            query = query.where(
                key >= last_value, sa.or_(key > last_value, sa.and_(key == last_value, Run.id > last_id))
            )
    order = (key.desc(), Run.id.desc()) if descending else (key.asc(), Run.id.asc())
    return [
        (run, value) for run, value in session.execute(query.add_columns(key).order_by(*order).limit(flt.limit + 1))
    ]


def list_robots(session: Session) -> list[tuple[Robot, int]]:
    """Robots with their number of runs."""
    counts = dict(
        session.execute(
            sa.select(Run.robot_id, sa.func.count()).where(Run.tier != Tier.DELETED).group_by(Run.robot_id)
        ).all()
    )
    return [(robot, int(counts.get(robot.id, 0))) for robot in queries.list_robots(session)]


# --- answers ------------------------------------------------------------------------------------


def robots_answer(catalog: sessionmaker[Session]) -> dict[str, Any]:
    """`GET /v1/robots`: robots and how many runs each has."""
    with session_scope(catalog) as session:
        return {
            "robots": [
                {
                    "id": robot.id,
                    "runs": count,
                    "created_at": iso_utc(robot.created_at),
                    "last_seen_at": iso_utc(robot.last_seen_at),
                }
                for robot, count in list_robots(session)
            ]
        }


def runs_answer(catalog: sessionmaker[Session], flt: RunFilter) -> dict[str, Any]:
    """`GET /v1/runs`: a page of runs and the cursor of the next one."""
    with session_scope(catalog) as session:
        page, next_cursor = list_runs(session, flt)
        return {"runs": [run_summary(run) for run in page], "next_cursor": next_cursor}


def run_summary(run: Run) -> dict[str, Any]:
    return {
        "id": run.id,
        "robot_id": run.robot_id,
        "application_id": run.application_id,
        "date": run.date.isoformat(),
        "status": run.status,
        "tier": run.tier,
        "started_at": iso_utc(run.started_at),
        "ended_at": iso_utc(run.ended_at),
        "last_data_at": iso_utc(run.last_data_at),
        "sdk_version": run.sdk_version,
        "chunks": run.chunks,
        "rows": run.rows,
        "bytes": run.bytes,
        "pinned": run.pinned,
        "pinned_by": run.pinned_by,
        "properties": json.loads(run.properties),
    }


def hot_lookup(ingest: IngestService | None, default_robot: str) -> HotLookup | None:
    """The lookup `run_answer` falls back on: this node's hot runs as ingest knows them (a run
    that names no robot is `default_robot`'s)."""
    if ingest is None:
        return None

    def lookup(run_id: str) -> queries.RunRecord | None:
        run = ingest.hot_run(run_id)
        return run.record(default_robot) if run is not None else None

    return lookup


def run_answer(
    catalog: sessionmaker[Session], run_id: str, policies: Policies | None, hot: HotLookup | None = None
) -> dict[str, Any]:
    """`GET /v1/runs/{run}`: one run with its entities, timelines, policy, lifecycle (`policies`:
    None where this node runs no retention), what its robot reports holding of it, its latest
    pulls, and what the corpus knows of it (metrics, tags, event counts, evaluation). A run hot
    here that the catalog has no row of yet (a stream just started or ended, the next catalog
    flush is up to FLEET_CATALOG_FLUSH_S away) is answered from `hot`, ingest's view, as the
    overview lists it from there: what a list shows, its page opens."""
    try:
        return _catalog_answer(catalog, run_id, policies)
    except NotFoundError:
        record = hot(run_id) if hot is not None else None
        if record is None:
            raise
        with session_scope(catalog) as session:  # live rules write a hot run's corpus rows before its row
            return {**hot_answer(record, policies), **corpus_answer(session, run_id)}


def hot_answer(record: queries.RunRecord, policies: Policies | None) -> dict[str, Any]:
    """`run_answer` for a hot run the catalog has no row of yet: nothing sealed, no events, no
    robot copy or pulls (both need the catalog's row)."""
    policy = policies.for_run(record.robot_id, record.application_id).to_dict() if policies is not None else None
    return {
        "id": record.id,
        "robot_id": record.robot_id,
        "application_id": record.application_id,
        "date": record.date.isoformat(),
        "status": str(record.status),
        "tier": str(record.tier),
        "started_at": iso_utc(record.started_at),
        "ended_at": iso_utc(record.ended_at),
        "last_data_at": iso_utc(record.last_data_at),
        "sdk_version": record.sdk_version,
        "chunks": record.chunks,
        "rows": record.rows,
        "bytes": record.bytes,
        "pinned": False,
        "pinned_by": None,
        "properties": record.properties,
        "entities": [entity_answer(e, e.archetypes, e.components) for e in record.entities],
        "timelines": [timeline_answer(t) for t in record.timelines],
        "policy": policy,
        "lifecycle": None,
        "objects": [],
        "events": [],
        "robot_copy": None,
        "pulls": [],
        "owner": None,
    }


def entity_answer(entity: Any, archetypes: list[str], components: list[str]) -> dict[str, Any]:
    """An entity of a run as GET /v1/runs/RUN shows it, from the catalog's row or ingest's record
    (which keep its archetypes and components as JSON text and as lists)."""
    return {
        "path": entity.path,
        "chunks": entity.chunks,
        "static_chunks": entity.static_chunks,
        "rows": entity.rows,
        "bytes": entity.bytes,
        "archetypes": archetypes,
        "components": components,
    }


def timeline_answer(timeline: Any) -> dict[str, Any]:
    return {"name": timeline.name, "type": timeline.type, "min": timeline.min, "max": timeline.max}


def _catalog_answer(catalog: sessionmaker[Session], run_id: str, policies: Policies | None) -> dict[str, Any]:
    with session_scope(catalog) as session:
        found = queries.require_run(session, run_id)
        return {
            **run_summary(found),
            "entities": [
                entity_answer(e, json.loads(e.archetypes), json.loads(e.components))
                for e in queries.run_entities(session, run_id)
            ],
            "timelines": [timeline_answer(t) for t in queries.run_timelines(session, run_id)],
            **_lifecycle(session, found, policies),
            **edge_queries.run_edge(session, run_id),  # the robot's own copy, and the latest pulls
            "owner": nodes.owner_of(session, [run_id]).get(run_id),  # the node filing it while hot (many nodes)
            **corpus_answer(session, run_id),
        }


def _lifecycle(session: Session, run: Run, policies: Policies | None) -> dict[str, Any]:
    """Where a sealed run's objects are, what retention did to it, and which policy applies."""
    life = queries.lifecycle(session, run.id)
    policy = policies.for_run(run.robot_id, run.application_id).to_dict() if policies is not None else None
    if life is None:
        return {"policy": policy, "lifecycle": None, "objects": [], "events": []}
    return {
        "policy": policy,
        "lifecycle": {
            "prefix": life.prefix,
            "promoted_at": iso_utc(life.promoted_at),
            "archived_at": iso_utc(life.archived_at),
            "archive_mode": life.archive_mode,
            "restore_state": life.restore_state,
            "restore_until": iso_utc(life.restore_until),
            "pinned_by": run.pinned_by,
            "deleted_at": iso_utc(life.deleted_at),
            "deleted_by": life.deleted_by,
            "deleted_policy": life.deleted_policy,
        },
        "objects": [
            {"name": o.name, "key": o.key, "tier": o.tier, "size": o.size, "sha256": o.sha256}
            for o in queries.run_objects(session, run.id).values()
        ],
        "events": [
            {"action": e.action, "at": iso_utc(e.occurred_at), "actor": e.actor, "policy": e.policy, "detail": e.detail}
            for e in queries.run_events(session, run.id)
        ],
    }
