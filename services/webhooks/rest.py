"""REST (admin): `POST /v1/webhooks`, `GET /v1/webhooks`, `DELETE /v1/webhooks/{id}`,
`GET /v1/webhooks/{id}/deliveries`. A new webhook's secret is in the answer to its creation, and
nowhere else, ever. Handlers parse, call the service, and leave errors to the app's one mapping."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Query, Request
from pydantic import BaseModel, Field

from catalog.webhooks import BODY_FORMATS, JSON
from services.auth.depends import actor, require
from services.auth.scopes import Principal, Scope
from services.webhooks import service
from services.webhooks.service import Webhooks

router = APIRouter()
Admin = Annotated[Principal, Depends(require(Scope.ADMIN))]


class WebhookRequest(BaseModel):
    url: str = Field(description="where occurrences are POSTed: a host listed in FLEET_WEBHOOK_HOSTS")
    on: list[str] = Field(description="what it is told of: event:KIND, event:*, run.sealed, robot.silent")
    format: str = Field(JSON, description=" | ".join(BODY_FORMATS) + " (slack: a Slack-compatible {text} body)")


def _hooks(request: Request) -> Webhooks:
    hooks: Webhooks = request.app.state.webhooks
    return hooks


@router.post("/v1/webhooks", status_code=201, summary="Add a webhook (its secret shown once, in this answer only)")
def add_webhook(request: Request, principal: Admin, body: Annotated[WebhookRequest, Body()]) -> dict[str, Any]:
    return service.add_webhook(_hooks(request), body.url, body.on, body.format, actor(request, principal))


@router.get("/v1/webhooks", summary="Webhooks: where each goes and what it is told of, never its secret")
def list_webhooks(request: Request, _: Admin) -> dict[str, Any]:
    return service.webhooks_answer(_hooks(request))


@router.delete("/v1/webhooks/{webhook_id}", summary="Remove a webhook; its pending deliveries are not sent")
def remove_webhook(request: Request, webhook_id: str, _: Admin) -> dict[str, Any]:
    return service.remove_webhook(_hooks(request), webhook_id)


@router.get("/v1/webhooks/{webhook_id}/deliveries", summary="A webhook's deliveries, newest first")
def deliveries(
    request: Request,
    webhook_id: str,
    _: Admin,
    limit: Annotated[int, Query(description=f"1 to {service.MAX_PAGE}")] = 50,
    cursor: Annotated[str | None, Query(description="`next_cursor` of the previous page")] = None,
) -> dict[str, Any]:
    return service.deliveries_answer(_hooks(request), webhook_id, limit, cursor)
