"""REST: `POST /v1/sql` (read-only SQL; JSON, CSV, Arrow IPC or Parquet by Accept or ?format=) and
`POST /v1/runs/{run}/analytics` (a hot run's analytics tables, now)."""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Query, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from services.analytics import service
from services.analytics.service import FORMATS
from services.auth.depends import limited, require
from services.auth.scopes import Principal, Scope

router = APIRouter()


class SqlRequest(BaseModel):
    query: str = Field(
        description="one SELECT over robots, runs, run_entities, run_timelines, run_metrics, events, run_tags, "
        "scalars, text_logs, transforms"
    )


@router.post(
    "/v1/sql",
    summary="Read-only SQL over the catalog and the analytics tables",
    responses={200: {"content": {media: {} for media in FORMATS.values()}}},
)
async def run_sql(
    request: Request,
    _: Annotated[Principal, Depends(limited("sql", Scope.READ))],
    body: Annotated[SqlRequest, Body()],
    fmt: Annotated[str | None, Query(alias="format", description=" | ".join(FORMATS) + " (default: by Accept)")] = None,
) -> Response:
    chosen = service.pick_format(fmt, request.headers.get("accept"))
    # async: the query runs in a worker process, the catalog snapshot on the SQL pool's own threads,
    # so waiting holds none of the threads the sync handlers (runs, uploads) share
    table = await service.query(request.app.state.analytics, body.query)  # busy: 429 with Retry-After
    encoded = await asyncio.to_thread(service.encode, table, chosen)  # JSON of 100,000 rows takes a while
    return Response(encoded, media_type=FORMATS[chosen], headers={"X-Row-Count": str(table.num_rows)})


@router.post("/v1/runs/{run_id}/analytics", summary="Write a hot run's analytics tables now")
def extract_run(
    request: Request, run_id: str, _: Annotated[Principal, Depends(require(Scope.WRITE))]
) -> dict[str, Any]:
    written = service.extract_hot_run(request.app.state.analytics, request.app.state.ingest, run_id)
    return {"run": run_id, "tables": written}
