"""REST: `GET /v1/robots`, `GET /v1/runs`, `GET /v1/runs/{run}`, `GET /v1/runs/{run}/recording.rrd`.
Handlers parse the request and call one service function; errors are mapped once by the app
(`FleetError` -> status)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import StreamingResponse

from services.runs import service
from services.runs.recording import RecordingQuery, open_recording
from services.runs.service import RunFilter, parse_properties, parse_time

router = APIRouter()


@router.get("/v1/robots", summary="Robots and how many runs each has")
def robots(request: Request) -> dict[str, Any]:
    return service.robots_answer(request.app.state.catalog)


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
    prop: Annotated[
        list[str] | None, Query(alias="property", description="NAME.FIELD=VALUE, e.g. fleet.robot_id=robot-7")
    ] = None,
    sort: Annotated[str, Query(description=" | ".join(service.SORTS))] = "-started_at",
    limit: Annotated[int, Query(description=f"1 to {service.MAX_LIMIT}")] = 100,
    cursor: Annotated[str | None, Query(description="`next_cursor` of the previous page")] = None,
) -> dict[str, Any]:
    flt = RunFilter(
        robot=robot or [],
        application=application or [],
        since=parse_time("since", since),
        until=parse_time("until", until),
        status=status,
        tier=tier,
        entity=entity or [],
        properties=parse_properties(prop or []),
        sort=sort,
        limit=limit,
        cursor=cursor,
    )
    return service.runs_answer(request.app.state.catalog, flt)


@router.get("/v1/runs/{run_id}", summary="One run: metadata, entities, timelines, sizes, tier")
def run(request: Request, run_id: str) -> dict[str, Any]:
    retention = request.app.state.retention
    return service.run_answer(request.app.state.catalog, run_id, retention.policies if retention else None)


@router.get(
    "/v1/runs/{run_id}/recording.rrd",
    summary="The run as an .rrd stream the Rerun viewer opens",
    response_class=StreamingResponse,
    responses={200: {"content": {"application/octet-stream": {}}}},
)
def recording(
    request: Request,
    run_id: str,
    include: Annotated[
        list[str] | None, Query(description="entity patterns to keep: /a/b or /a/** (repeatable)")
    ] = None,
    exclude: Annotated[list[str] | None, Query(description="entity patterns to drop; wins over include")] = None,
    blueprint: Annotated[bool, Query(description="include the run's blueprint")] = True,
    timeline: Annotated[str | None, Query(description="keep chunks overlapping [start, end] on this timeline")] = None,
    start: Annotated[
        str | None,
        Query(description="sequence number, duration (12.5s) or timestamp (ISO-8601 or ns), by the timeline's type"),
    ] = None,
    end: Annotated[str | None, Query(description="as start; inclusive")] = None,
    latest_at: Annotated[
        bool,
        Query(
            description="also the newest data before start, per entity and component, so the scene at start is complete"
        ),
    ] = True,
    follow: Annotated[
        bool,
        Query(
            description="keep the response open and send new chunks until the run closes: a live view over plain HTTP"
        ),
    ] = False,
    exact: Annotated[
        bool,
        Query(
            description="cut chunks to the rows inside the window (re-encoded, new "
            "chunk ids); otherwise whole chunks that overlap it"
        ),
    ] = False,
) -> StreamingResponse:
    """`rerun "http://HOST:8080/v1/runs/RUN/recording.rrd?include=/world/**"` opens it in the viewer.
    Static data is always kept unless its entity is excluded; payloads are copied untouched."""
    tiers = getattr(request.app.state, "tiers", None)  # none on a node without retention: hot runs only
    found = open_recording(
        request.app.state.ingest,
        request.app.state.catalog,
        tiers.warm if tiers else None,
        run_id,
        RecordingQuery(include or [], exclude or [], blueprint, timeline, start, end, latest_at, follow, exact),
    )
    return StreamingResponse(
        found.body,
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{found.filename}"', "ETag": found.etag},
    )
