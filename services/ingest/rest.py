"""REST: `POST /v1/uploads`, an `.rrd` body streamed into the ingest service (or, if another node
of the depot owns its run, relayed to that node as it arrives)."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse, Response
from starlette.requests import ClientDisconnect

from core.errors import FleetError
from services.auth.depends import require
from services.auth.scopes import Principal, Scope
from services.cluster.relay import request_of
from services.ingest.routing import relay_source
from services.ingest.service import IngestService
from services.ingest.source import Source
from services.rrd.decoder import RrdDecoder
from services.rrd.messages import Event

log = logging.getLogger(__name__)
router = APIRouter()


@router.post(
    "/v1/uploads",
    summary="Upload an .rrd file (idempotent: chunks already held are skipped)",
    responses={
        400: {"description": "the body is not valid RRD from the byte named on"},
        503: {"description": "the node that owns the run does not answer yet: send again in a few seconds"},
        507: {"description": "the hot tier is full"},
    },
)
async def upload(request: Request, principal: Annotated[Principal, Depends(require(Scope.INGEST, Scope.WRITE))]) -> Any:
    """Streams the body (any size, constant memory) into the runs it names. Answers the runs
    touched, chunks new and duplicate, and bytes; `catalog` is "pending" if the catalog could not
    be written in time (the data is kept, and the catalog catches up). If the body turns bad part-way, the chunks
    before the fault are kept and the answer (4xx) names the byte offset; a client gone mid-body
    likewise keeps the chunks that came whole, and its runs are closed. A robot's ingest token files
    the runs under its robot only; a `write` token uploads for any robot."""
    service: IngestService = request.app.state.ingest
    settings = request.app.state.settings
    decoder = RrdDecoder(max_message_size=settings.max_message_size, max_chunk_bytes=settings.max_chunk_bytes)
    source = service.open_source(live=False, robot=principal.robot)

    async def events() -> AsyncIterator[Event]:
        async for piece in request.stream():
            for event in decoder.feed(piece):
                yield event
        for event in decoder.finish():
            yield event

    try:
        body = events()
        async for event in body:
            await service.prepare(source, event)
            if source.relay_to is not None:
                answer = await _relayed(service, source, request, event, body)
                if answer is not None:
                    service.close_source(source)
                    return answer
            service.accept(source, event)
    except FleetError as exc:
        report = await service.finish_upload(source)
        body_json = {**exc.to_dict(), "offset": getattr(exc, "offset", None), "accepted": report.to_dict()}
        return JSONResponse(body_json, status_code=exc.http_status(), headers=exc.headers())
    except ClientDisconnect:
        return await _client_gone(service, source)
    return (await service.finish_upload(source)).to_dict()


async def _client_gone(service: IngestService, source: Source) -> Response:
    """The client went away mid-body: what came whole is kept (sending the file again completes it,
    chunks held being skipped) and its runs are closed, as at the end of any upload. One log line,
    no traceback: a dropped connection is the client's doing, not a fault of the depot."""
    report = await service.finish_upload(source)
    log.info(
        "upload ended by its client mid-body: kept %d new chunks of runs %s; sending it again completes them",
        report.chunks_new,
        ", ".join(report.runs) or "(none)",
    )
    return Response(status_code=499)  # nobody reads it: nginx's "client closed request"


async def _relayed(
    service: IngestService, source: Source, request: Request, first: Event, rest: AsyncIterator[Event]
) -> dict[str, Any] | None:
    """The rest of the upload sent to the node that owns its run, and that node's answer; None if
    this node took the run over meanwhile (it files the upload itself)."""
    auth = request.headers.get("authorization")

    async def requests() -> AsyncIterator[bytes]:
        async for event in rest:
            if (message := request_of(event)) is not None:
                yield message

    metadata = [("authorization", auth)] if auth else []
    return await relay_source(service, request.app.state.auth, source, metadata, [first], requests())
