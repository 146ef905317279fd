"""REST: `POST /v1/uploads`, an `.rrd` body streamed into the ingest service."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import JSONResponse

from core.errors import FleetError
from services.auth.depends import require
from services.auth.scopes import Principal, Scope
from services.ingest.service import IngestService
from services.rrd.decoder import RrdDecoder

router = APIRouter()


@router.post(
    "/v1/uploads",
    summary="Upload an .rrd file (idempotent: chunks already held are skipped)",
    responses={
        400: {"description": "the body is not valid RRD from the byte named on"},
        507: {"description": "the hot tier is full"},
    },
)
async def upload(request: Request, principal: Annotated[Principal, Depends(require(Scope.INGEST, Scope.WRITE))]) -> Any:
    """Streams the body (any size, constant memory) into the runs it names. Answers the runs
    touched, chunks new and duplicate, and bytes; `catalog` is "pending" if the catalog could not
    be written in time (the data is kept, and the catalog catches up). If the body turns bad part-way, the chunks
    before the fault are kept and the answer (4xx) names the byte offset. A robot's ingest token files
    the runs under its robot only; a `write` token uploads for any robot."""
    service: IngestService = request.app.state.ingest
    settings = request.app.state.settings
    decoder = RrdDecoder(max_message_size=settings.max_message_size, max_chunk_bytes=settings.max_chunk_bytes)
    source = service.open_source(live=False, robot=principal.robot)
    try:
        async for piece in request.stream():
            for event in decoder.feed(piece):
                await service.prepare(source, event)
                service.accept(source, event)
        for event in decoder.finish():
            await service.prepare(source, event)
            service.accept(source, event)
    except FleetError as exc:
        report = await service.finish_upload(source)
        body = {**exc.to_dict(), "offset": getattr(exc, "offset", None), "accepted": report.to_dict()}
        return JSONResponse(body, status_code=exc.http_status())
    return (await service.finish_upload(source)).to_dict()
