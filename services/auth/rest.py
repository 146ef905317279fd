"""REST: `GET /v1/whoami`, and tokens (`POST /v1/tokens`, `GET /v1/tokens`, `DELETE /v1/tokens/{id}`,
admin only). A new token is in the answer to its creation, and nowhere else, ever."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any

from fastapi import APIRouter, Body, Depends, Query, Request
from pydantic import BaseModel, Field

from services.auth.depends import actor, require
from services.auth.scopes import Principal, Scope
from services.auth.tokens import Auth, token_answer

router = APIRouter()
Admin = Annotated[Principal, Depends(require(Scope.ADMIN))]
AnyToken = Annotated[Principal, Depends(require(*Scope))]


class TokenRequest(BaseModel):
    scopes: list[str] = Field(description="ingest (with robot), read, write, admin")
    name: str | None = Field(None, description="who acts with it (the actor in events); default: the robot id")
    robot: str | None = Field(None, description="the robot an ingest token writes runs for")
    expires_in_s: float | None = Field(None, gt=0, description="seconds until it expires (default: never)")
    hosts: list[str] | None = Field(
        None, description="allowed_hosts: hosts Rerun clients send it to (default: FLEET_PUBLIC_HOSTS)"
    )


def _auth(request: Request) -> Auth:
    auth: Auth = request.app.state.auth
    return auth


@router.get("/v1/whoami", summary="Who the token stands for and what it may do")
def whoami(request: Request, principal: AnyToken) -> dict[str, Any]:
    return {
        "subject": principal.subject,
        "scopes": sorted(s.value for s in principal.scopes),
        "granted": sorted(s.value for s in principal.granted),
        "robot": principal.robot,
        "token": principal.token_id,
        "auth": "on" if _auth(request).enabled else "off",
    }


@router.post("/v1/tokens", status_code=201, summary="Create a token (shown once, in this answer only)")
def create_token(request: Request, principal: Admin, body: Annotated[TokenRequest, Body()]) -> dict[str, Any]:
    issued = _auth(request).issue(
        subject=body.name or body.robot or "",
        scopes=body.scopes,
        robot=body.robot,
        expires_in=dt.timedelta(seconds=body.expires_in_s) if body.expires_in_s else None,
        hosts=body.hosts,
        created_by=actor(request, principal),
    )
    return {**token_answer(issued.record), "allowed_hosts": issued.allowed_hosts, "token": issued.token}


@router.get("/v1/tokens", summary="Tokens: what each grants, never the token itself")
def list_tokens(
    request: Request,
    _: Admin,
    revoked: Annotated[bool, Query(description="also revoked tokens")] = False,
) -> dict[str, Any]:
    return {"tokens": [token_answer(r) for r in _auth(request).tokens(include_revoked=revoked)]}


@router.delete("/v1/tokens/{token_id}", summary="Revoke a token: refused everywhere within FLEET_AUTH_CACHE_S")
def revoke_token(request: Request, token_id: str, principal: Admin) -> dict[str, Any]:
    return token_answer(_auth(request).revoke(token_id, actor(request, principal)))
