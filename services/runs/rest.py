"""REST: `GET /v1/robots`, `GET /v1/runs`, `GET /v1/runs/{run}`. Handlers parse, call the runs
service, and shape JSON; errors are mapped once by the app (`FleetError` -> status)."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import StreamingResponse
from sqlalchemy.orm import Session

from catalog import queries
from catalog.db import session_scope
from catalog.models import Run
from core.clock import iso_utc
from core.errors import BadParameterError
from services.runs import download, sealed, service
from services.runs.service import RunFilter, parse_properties, parse_time
from services.sealed.read import locate_sealed

router = APIRouter()


def run_summary(run: Run) -> dict[str, Any]:
    return {
        "id": run.id, "robot_id": run.robot_id, "application_id": run.application_id,
        "date": run.date.isoformat(), "status": run.status, "tier": run.tier,
        "started_at": iso_utc(run.started_at), "ended_at": iso_utc(run.ended_at),
        "last_data_at": iso_utc(run.last_data_at), "sdk_version": run.sdk_version,
        "chunks": run.chunks, "rows": run.rows, "bytes": run.bytes, "pinned": run.pinned,
        "pinned_by": run.pinned_by,
        "properties": json.loads(run.properties),
    }


@router.get("/v1/robots", summary="Robots and how many runs each has")
def robots(request: Request) -> dict[str, Any]:
    with session_scope(request.app.state.catalog) as session:
        return {"robots": [{"id": robot.id, "runs": count, "created_at": iso_utc(robot.created_at),
                            "last_seen_at": iso_utc(robot.last_seen_at)}
                           for robot, count in service.list_robots(session)]}


@router.get("/v1/runs", summary="Runs, filtered, sorted, a page at a time")
def runs(
    request: Request,
    robot: Annotated[list[str] | None, Query(description="robot id (repeatable)")] = None,
    application: Annotated[list[str] | None, Query(description="application id (repeatable)")] = None,
    since: Annotated[str | None, Query(description="started at or after (ISO-8601)")] = None,
    until: Annotated[str | None, Query(description="started before (ISO-8601)")] = None,
    status: Annotated[str | None, Query(description=" | ".join(service.STATUSES))] = None,
    tier: Annotated[str | None, Query(description=" | ".join(service.TIERS))] = None,
    entity: Annotated[list[str] | None, Query(description="has an entity: `/world/**` or an exact path")] = None,
    prop: Annotated[list[str] | None, Query(alias="property",
                                            description="NAME.FIELD=VALUE, e.g. fleet.robot_id=robot-7")] = None,
    sort: Annotated[str, Query(description=" | ".join(service.SORTS))] = "-started_at",
    limit: Annotated[int, Query(description=f"1 to {service.MAX_LIMIT}")] = 100,
    cursor: Annotated[str | None, Query(description="`next_cursor` of the previous page")] = None,
) -> dict[str, Any]:
    flt = RunFilter(robot=robot or [], application=application or [], since=parse_time("since", since),
                    until=parse_time("until", until), status=status, tier=tier, entity=entity or [],
                    properties=parse_properties(prop or []), sort=sort, limit=limit, cursor=cursor)
    with session_scope(request.app.state.catalog) as session:
        page, next_cursor = service.list_runs(session, flt)
        return {"runs": [run_summary(run) for run in page], "next_cursor": next_cursor}


@router.get("/v1/runs/{run_id}", summary="One run: metadata, entities, timelines, sizes, tier")
def run(request: Request, run_id: str) -> dict[str, Any]:
    with session_scope(request.app.state.catalog) as session:
        found = queries.require_run(session, run_id)
        return {
            **run_summary(found),
            "entities": [{"path": e.path, "chunks": e.chunks, "static_chunks": e.static_chunks, "rows": e.rows,
                          "bytes": e.bytes, "archetypes": json.loads(e.archetypes),
                          "components": json.loads(e.components)}
                         for e in queries.run_entities(session, run_id)],
            "timelines": [{"name": t.name, "type": t.type, "min": t.min, "max": t.max}
                          for t in queries.run_timelines(session, run_id)],
            **_lifecycle(request, session, found),
        }


def _lifecycle(request: Request, session: Session, run: Run) -> dict[str, Any]:
    """Where a sealed run's objects are, what retention did to it, and which policy applies."""
    life = queries.lifecycle(session, run.id)
    retention = request.app.state.retention
    policy = retention.policies.for_run(run.robot_id, run.application_id).to_dict() if retention else None
    if life is None:
        return {"policy": policy, "lifecycle": None, "objects": [], "events": []}
    return {
        "policy": policy,
        "lifecycle": {"prefix": life.prefix, "promoted_at": iso_utc(life.promoted_at),
                      "archived_at": iso_utc(life.archived_at), "archive_mode": life.archive_mode,
                      "restore_state": life.restore_state, "restore_until": iso_utc(life.restore_until),
                      "pinned_by": run.pinned_by, "deleted_at": iso_utc(life.deleted_at),
                      "deleted_by": life.deleted_by, "deleted_policy": life.deleted_policy},
        "objects": [{"name": o.name, "key": o.key, "tier": o.tier, "size": o.size, "sha256": o.sha256}
                    for o in queries.run_objects(session, run.id).values()],
        "events": [{"action": e.action, "at": iso_utc(e.occurred_at), "actor": e.actor, "policy": e.policy,
                    "detail": e.detail} for e in queries.run_events(session, run.id)],
    }


@router.get("/v1/runs/{run_id}/recording.rrd", summary="The run as an .rrd stream the Rerun viewer opens",
            response_class=StreamingResponse,
            responses={200: {"content": {"application/octet-stream": {}}}})
def recording(
    request: Request,
    run_id: str,
    include: Annotated[list[str] | None, Query(description="entity patterns to keep: /a/b or /a/** (repeatable)")]
    = None,
    exclude: Annotated[list[str] | None, Query(description="entity patterns to drop; wins over include")] = None,
    blueprint: Annotated[bool, Query(description="include the run's blueprint")] = True,
    timeline: Annotated[str | None, Query(description="keep chunks overlapping [start, end] on this timeline")]
    = None,
    start: Annotated[str | None, Query(description="sequence number, duration (12.5s) or timestamp "
                                                   "(ISO-8601 or ns), by the timeline's type")] = None,
    end: Annotated[str | None, Query(description="as start; inclusive")] = None,
    latest_at: Annotated[bool, Query(description="also the newest data before start, per entity and "
                                                 "component, so the scene at start is complete")] = True,
    follow: Annotated[bool, Query(description="keep the response open and send new chunks until the run "
                                              "closes: a live view over plain HTTP")] = False,
    exact: Annotated[bool, Query(description="cut chunks to the rows inside the window (re-encoded, new "
                                             "chunk ids); otherwise whole chunks that overlap it")] = False,
) -> StreamingResponse:
    """`rerun "http://HOST:8080/v1/runs/RUN/recording.rrd?include=/world/**"` opens it in the viewer.
    Static data is always kept unless its entity is excluded; payloads are copied untouched."""
    entities = download.EntityFilter(include or [], exclude or [])
    ingest = request.app.state.ingest
    hot = ingest.hot_recording(run_id) if ingest is not None else None
    if hot is not None:
        types, size = hot.timeline_types, hot.size
    else:  # 404 naming the run, 409 for a cold run not restored, 410 for a deleted one
        found = locate_sealed(request.app.state.catalog, request.app.state.tiers.warm, run_id,
                                     dt.datetime.now(dt.UTC))
        types, size = found.timeline_types(), found.size
    window = download.window_from_query(types, timeline, start, end, latest_at, exact)
    if follow and window is not None:
        raise BadParameterError("follow", "follow=true streams what comes next: it takes no time window")
    filters = json.dumps([sorted(entities.include), sorted(entities.exclude), blueprint, repr(window)])
    etag = f'"{run_id}-{size}-{hashlib.sha256(filters.encode()).hexdigest()[:16]}"'
    if hot is not None:
        body = download.stream_run(hot.path, hot.size, entities, blueprint=blueprint, window=window,
                                   follow=hot.follow if follow else None)
    else:
        body = sealed.stream_sealed(found, entities, blueprint=blueprint, window=window)
    return StreamingResponse(body, media_type="application/octet-stream",
                             headers={"Content-Disposition": f'attachment; filename="{run_id}.rrd"', "ETag": etag})
