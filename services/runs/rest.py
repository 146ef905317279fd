"""REST: `GET /v1/robots`, `GET /v1/runs`, `GET /v1/runs/{run}`, `GET /v1/runs/{run}/recording.rrd`.
Handlers parse the request and call one service function; errors are mapped once by the app
(`FleetError` -> status)."""

from __future__ import annotations

import asyncio
import dataclasses
import json
from collections.abc import AsyncIterator, Iterator
from typing import Annotated, Any, cast

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import StreamingResponse

from core.errors import NotFoundError, OwnerDownError
from services.auth.depends import recording_reader, require
from services.auth.scopes import Principal, Scope
from services.auth.standing import GrantWatch, while_granted
from services.cluster import peer
from services.ingest.routing import asking_for, owner_down, owner_elsewhere
from services.rrd.frames import MessageKind, encode_message_header
from services.runs import links, service
from services.runs.recording import RecordingQuery, recording_download
from services.runs.sealed import WholeOnLoop
from services.runs.sending import WholeObjectResponse, in_slices
from services.runs.service import RunFilter, parse_properties, parse_time

router = APIRouter()
Reader = Annotated[Principal, Depends(require(Scope.READ))]
# What a followed run's stream ends with when what let it in ends first: an End message (no footer),
# so the viewer sees a recording that ended, not one cut off.
END = encode_message_header(MessageKind.END, 0)
WARNINGS_HEADER = "Fleet-Warnings"


@router.get("/v1/robots", summary="Robots and how many runs each has")
def robots(request: Request, _: Reader) -> dict[str, Any]:
    return service.robots_answer(request.app.state.catalog)


@router.get("/v1/runs", summary="Runs, filtered, sorted, a page at a time")
def runs(
    request: Request,
    _: Reader,
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
    metric: Annotated[
        list[str] | None,
        Query(description="NAME OP VALUE, OP one of > >= < <= = != (e.g. distance_m>100; repeatable: all hold)"),
    ] = None,
    tag: Annotated[list[str] | None, Query(description="has this tag (repeatable: all of them)")] = None,
    event: Annotated[
        list[str] | None, Query(description="has at least one event of this kind (repeatable: each of them)")
    ] = None,
    sort: Annotated[str, Query(description=" | ".join(service.SORT_FORMS))] = "-started_at",
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
        metric=metric or [],
        tag=tag or [],
        event=event or [],
        sort=sort,
        limit=limit,
        cursor=cursor,
    )
    return service.runs_answer(request.app.state.catalog, flt)


@router.get("/v1/runs/{run_id}", summary="One run: metadata, entities, timelines, sizes, tier")
def run(request: Request, run_id: str, _: Reader) -> dict[str, Any]:
    state = request.app.state
    hot = service.hot_lookup(state.ingest, state.node.default_robot)  # the view the overview lists hot runs from
    return service.run_answer(state.catalog, run_id, state.retention.policies if state.retention else None, hot)


@router.get(
    "/v1/runs/{run_id}/recording.rrd",
    summary="The run as an .rrd stream the Rerun viewer opens",
    response_class=StreamingResponse,
    responses={
        200: {"content": {"application/octet-stream": {}}},
        503: {"description": "the run is hot on another node, its owner (named), which does not answer"},
    },
)
async def recording(
    request: Request,
    run_id: str,
    principal: Annotated[Principal, Depends(recording_reader)],
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
    Static data is always kept unless its entity is excluded; payloads are copied untouched. Needs a
    `read` token, or a signed link (`POST /v1/runs/RUN/links`) for clients that send no header."""
    node = request.app.state.node
    ingest = request.app.state.ingest
    query = RecordingQuery(include or [], exclude or [], blueprint, timeline, start, end, latest_at, follow, exact)
    owner = await owner_elsewhere(ingest, run_id)
    if owner is not None:  # hot on another node of the depot: streamed from there
        asked = {"run_id": run_id, **dataclasses.asdict(query)}
        body = await first_piece(peer.read_hot(node.channels, owner, asked, asking_for(ingest, node.auth, principal)))
        disposition = f'attachment; filename="{run_id}.rrd"'
        return StreamingResponse(
            until_grant_ends(request, principal, body) if follow else body,
            media_type="application/octet-stream",
            headers={"Content-Disposition": disposition},
        )
    try:
        found = await asyncio.to_thread(recording_download, ingest, node.catalog, node.tiers.warm, run_id, query)
    except NotFoundError:  # not here; if its owner is down the run is there, not missing: 503 naming it
        down = await owner_down(ingest, run_id) if ingest is not None else None
        if down is None:
            raise
        raise OwnerDownError(run_id, down.node_id, down.peer_addr) from None
    headers = {
        "Content-Disposition": f'attachment; filename="{found.filename}"',
        "ETag": found.etag,
        **warnings_header(found.warnings),
        # (a client shows progress; the server sends the body as it is, without chunked framing)
        **({"Content-Length": str(found.size)} if found.size is not None else {}),
    }
    if isinstance(found.body, WholeOnLoop):  # the sealed object itself: the kernel may move it
        return WholeObjectResponse(found.body, headers)
    followed = follow and isinstance(found.body, AsyncIterator)  # a hot run: as long as it is live
    return StreamingResponse(
        in_slices(until_grant_ends(request, principal, found.body) if followed else found.body),
        media_type="application/octet-stream",
        headers=headers,
    )


def warnings_header(warnings: list[str]) -> dict[str, str]:
    """`Fleet-Warnings`: a JSON list (ASCII, so any pattern fits a header) of filters that match no
    entity of the run; the answer is still the run as asked, so a client may show them."""
    return {WARNINGS_HEADER: json.dumps(warnings)} if warnings else {}


def until_grant_ends(
    request: Request, principal: Principal, body: Iterator[bytes | memoryview] | AsyncIterator[bytes | memoryview]
) -> AsyncIterator[bytes]:
    """A followed run's stream, ended (with an End message) when what let it in does: its token
    revoked or expired, its signed link expired; checked while it runs (`services.auth.standing`)."""
    assert isinstance(body, AsyncIterator)
    followed = cast(AsyncIterator[bytes], body)  # a hot run followed: its pieces are bytes
    watch = GrantWatch(request.app.state.auth, principal, request.state.surface)
    return while_granted(watch, followed, closing=END) if watch.watched else followed


async def first_piece(pieces: AsyncIterator[bytes]) -> AsyncIterator[bytes]:
    """`pieces` with its first one already read: a refusal (the run not found, a bad parameter)
    becomes the answer's status rather than a cut-off stream."""
    first = await anext(pieces, b"")

    async def rest() -> AsyncIterator[bytes]:
        yield first
        async for piece in pieces:
            yield piece

    return rest()


@router.post(
    "/v1/runs/{run_id}/links",
    summary="A signed, expiring link to the run's recording, for clients that send no header",
)
def recording_link(
    request: Request,
    run_id: str,
    principal: Reader,
    expires_in: Annotated[
        float | None, Query(description="seconds the link lasts (default FLEET_LINK_TTL_S; at most 7 days)")
    ] = None,
) -> dict[str, Any]:
    """Takes the recording's parameters (include, exclude, timeline, start, end, ...) as query
    parameters and answers `{url, expires_at}`: `rerun URL`, the web viewer or a browser open it as
    is. Changing any parameter breaks it; revoking the token that asked ends it."""
    settings = request.app.state.settings
    params = [(k, v) for k, v in request.query_params.multi_items() if k != "expires_in"]
    return links.recording_link(
        request.app.state.auth,
        principal,
        links.RunLookup(request.app.state.ingest, request.app.state.catalog),
        run_id,
        params,
        links.lifetime(expires_in, settings.link_ttl_s),
        links.request_base(request),
    )
