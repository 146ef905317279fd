"""REST: uploads (`POST /v1/uploads`: an `.rrd` or an MCAP file, told apart by its first bytes) and
imports (`/v1/imports`: every upload with its state; a failed MCAP import retried, or its original
fetched by an admin). Handlers parse, call the importer and map errors."""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import JSONResponse, Response, StreamingResponse

from services.auth.depends import actor, require
from services.auth.scopes import Principal, Scope
from services.imports import records
from services.imports.mcap_import import Converter
from services.imports.records import Ledger
from services.imports.service import Importer, UploadAsk
from services.storage.objectstore import RangeReader

router = APIRouter()
Reader = Annotated[Principal, Depends(require(Scope.READ))]
Writer = Annotated[Principal, Depends(require(Scope.WRITE))]
Admin = Annotated[Principal, Depends(require(Scope.ADMIN))]
ImportId = Annotated[str, Path(max_length=64)]


def ledger(request: Request) -> Ledger:
    return Ledger.of(request.app.state.node)


def importer(request: Request) -> Importer:
    """The importer of this app's node (its ingest service, auth, ledger, converter): what the
    upload, retry and the console's Retry button use."""
    state = request.app.state
    settings = state.node.settings
    return Importer(
        state.ingest,
        state.auth,
        ledger(request),
        Converter.of(settings),
        settings.max_message_size,
        settings.max_chunk_bytes,
    )


@router.post(
    "/v1/uploads",
    summary="Upload an .rrd or MCAP file (idempotent: what the depot holds is skipped)",
    responses={
        400: {
            "description": "the body is not valid RRD from the byte named on, or not an MCAP file the depot converts"
        },
        409: {"description": "the same MCAP file is being filed by another upload, or is an earlier copy of one held"},
        413: {"description": "the MCAP conversion went past its time, memory or output limit"},
        503: {"description": "the node that owns the run does not answer yet: send again in a few seconds"},
        507: {"description": "the hot tier is full"},
    },
)
async def upload(
    request: Request,
    principal: Annotated[Principal, Depends(require(Scope.INGEST, Scope.WRITE))],
    name: Annotated[str, Query(max_length=256, description="the file's name, as the import lists it")] = "",
    run_id: Annotated[str | None, Query(max_length=128, description="MCAP: the run to file it as")] = None,
    application: Annotated[str | None, Query(max_length=256, description="MCAP: its application id (mcap)")] = None,
    robot: Annotated[str | None, Query(max_length=128, description="MCAP: its robot, for a write token")] = None,
) -> Any:
    """An `.rrd` body is streamed into the runs it names (any size, constant memory). An MCAP body
    (ROS 2 bag, Foxglove) is kept, converted by the Rerun CLI and filed the same way; the same file
    twice is filed once (`already_held`). Answers the runs touched, chunks new and duplicate, bytes,
    and the import (`GET /v1/imports/ID`). If an `.rrd` body turns bad part-way, the chunks before the
    fault are kept and the answer (4xx) names the byte offset. A robot's ingest token files the runs
    under its robot only; a `write` token uploads for any robot."""
    ask = UploadAsk(name, run_id, application, robot)
    filed = await importer(request).upload(
        request.stream(), principal, actor(request, principal), request.headers.get("authorization"), ask
    )
    if filed.status == 200:
        return filed.body
    return JSONResponse(filed.body, status_code=filed.status, headers=filed.headers)


@router.get("/v1/imports", summary="Uploads, RRD and MCAP, newest first, with their state and why one failed")
def listed(
    request: Request,
    _: Reader,
    state: Annotated[str | None, Query(max_length=16, description="receiving, converting, filed or failed")] = None,
    kind: Annotated[str | None, Query(max_length=8, description="rrd or mcap")] = None,
    robot: Annotated[str | None, Query(max_length=128)] = None,
    limit: Annotated[int, Query(description="at most this many (1 to 500)")] = 100,
    before: Annotated[str | None, Query(max_length=64, description="the page after this import")] = None,
) -> dict[str, Any]:
    return records.listed(request.app.state.catalog, state=state, kind=kind, robot=robot, limit=limit, before=before)


@router.get("/v1/imports/{import_id}", summary="One import")
def one(request: Request, import_id: ImportId, _: Reader) -> dict[str, Any]:
    return records.import_json(ledger(request).row(import_id))


@router.post(
    "/v1/imports/{import_id}/retry", summary="Convert a failed MCAP import again from its quarantined original"
)
async def retry(request: Request, import_id: ImportId, _: Writer) -> Any:
    filed = await importer(request).retry(import_id, request.headers.get("authorization"))
    if filed.status == 200:
        return filed.body
    return JSONResponse(filed.body, status_code=filed.status, headers=filed.headers)


@router.get("/v1/imports/{import_id}/original", summary="A failed MCAP import's original file, from quarantine")
async def original(request: Request, import_id: ImportId, _: Admin) -> Response:
    return await original_download(ledger(request), import_id)


async def original_download(found: Ledger, import_id: str) -> StreamingResponse:
    """A failed import's quarantined original as a download (an attachment named after its file);
    NOT_FOUND if it keeps none. The REST route and the console's link both answer with it."""
    key, size, name = await asyncio.to_thread(records.quarantined, found, import_id)
    reader = RangeReader(found.warm, key, size)

    async def pieces() -> Any:
        while piece := await asyncio.to_thread(reader.read, 8 << 20):
            yield piece

    headers = {"Content-Length": str(size), "Content-Disposition": f'attachment; filename="{name}"'}
    return StreamingResponse(pieces(), media_type="application/octet-stream", headers=headers)
