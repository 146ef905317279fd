"""REST for scripts: saved queries (what the console's dashboards draw). `GET /v1/queries` (read),
`POST /v1/queries` (write), `GET /v1/queries/{id}` (read: with its answer now, JSON as `/v1/sql`
answers), `DELETE /v1/queries/{id}` (write)."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Depends, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from services.analytics import saved, service
from services.analytics.service import Analytics
from services.auth.depends import limited, require
from services.auth.scopes import Principal, Scope

router = APIRouter(tags=["queries"])


class NewQuery(BaseModel):
    name: str = Field(description="unique: the chart's title on the dashboards", max_length=saved.NAME_LENGTH)
    sql: str = Field(description="one SELECT, as POST /v1/sql takes it", examples=[saved.EXAMPLE])
    chart: Literal["line", "bar", "table"] = Field("table", description="how the dashboards draw its answer")


def _ctx(request: Request) -> Analytics:
    ctx: Analytics = request.app.state.analytics
    return ctx


@router.get("/v1/queries", summary="Saved queries (the console's dashboards)")
def list_queries(request: Request, _: Annotated[Principal, Depends(require(Scope.READ))]) -> dict[str, Any]:
    return {"queries": [q.to_dict() for q in saved.saved(_ctx(request))]}


@router.post("/v1/queries", status_code=201, summary="Save a query (it must run; its name must be free)")
async def save_query(
    request: Request,
    principal: Annotated[Principal, Depends(limited("sql", Scope.WRITE))],
    body: Annotated[NewQuery, Body()],
) -> dict[str, Any]:
    ctx = _ctx(request)
    await service.query(ctx, body.sql)  # a query that fails is not saved: its error answers
    record = await asyncio.to_thread(saved.save, ctx, body.name, body.sql, body.chart, principal.subject)
    return record.to_dict()


@router.get("/v1/queries/{query_id}", summary="A saved query and its answer now")
async def get_query(
    request: Request, query_id: str, _: Annotated[Principal, Depends(limited("sql", Scope.READ))]
) -> Response:
    ctx = _ctx(request)
    record = await asyncio.to_thread(saved.one, ctx, query_id)
    table = await service.query(ctx, record.sql)
    answer = json.loads(await asyncio.to_thread(service.encode, table, "json"))
    return Response(json.dumps({**record.to_dict(), "answer": answer}), media_type="application/json")


@router.delete("/v1/queries/{query_id}", summary="Delete a saved query")
def delete_query(
    request: Request, query_id: str, _: Annotated[Principal, Depends(require(Scope.WRITE))]
) -> dict[str, Any]:
    return {"deleted": saved.delete(_ctx(request), query_id).to_dict()}
