"""REST: the token of a request (`Authorization: Bearer`) checked against the scope a route needs,
as FastAPI dependencies; routes declare `Depends(require(Scope.READ))` and take the principal."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from services.auth.links import SIGNATURE
from services.auth.ratelimit import RateLimits
from services.auth.scopes import Principal, Scope
from services.auth.standing import LINK
from services.auth.tokens import Auth

REST = "rest"  # the surface of requests with a token in their header, as refusals are counted

bearer = HTTPBearer(
    auto_error=False,
    description="a token of this depot: `fleet tokens create`, or DATA_DIR/admin.token on the depot's machine",
)
Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]


def _auth(request: Request) -> Auth:
    auth: Auth = request.app.state.auth
    return auth


def _checked(
    request: Request, credentials: HTTPAuthorizationCredentials | None, scopes: tuple[Scope, ...]
) -> Principal:
    auth = _auth(request)
    principal = auth.authenticate(credentials.credentials if credentials else None, REST)
    return auth.authorize(principal, REST, *scopes)


def require(*scopes: Scope) -> Callable[[Request, HTTPAuthorizationCredentials | None], Principal]:
    """A dependency: the request's principal if its token holds one of `scopes` (401 without a valid
    token, 403 without the scope)."""

    def principal(request: Request, credentials: Credentials) -> Principal:
        return _checked(request, credentials, scopes)

    return principal


def limited(kind: str, *scopes: Scope) -> Callable[[Request, HTTPAuthorizationCredentials | None], Principal]:
    """As `require`, and counted against the token's rate limit of `kind` (429 past it)."""

    def principal(request: Request, credentials: Credentials) -> Principal:
        checked = _checked(request, credentials, scopes)
        rate_limits(request).hit(kind, checked)
        return checked

    return principal


def recording_reader(request: Request, run_id: str, credentials: Credentials) -> Principal:
    """A recording is read with a `read` token, or by a signed link to it (no header needed); which
    of them let the request in is its `surface` (what a stream that outlives it is checked as)."""
    if credentials is None and SIGNATURE in request.query_params:
        principal = _auth(request).link_principal(run_id, list(request.query_params.multi_items()))
        request.state.surface = LINK
    else:
        principal = _checked(request, credentials, (Scope.READ,))
        request.state.surface = REST
    rate_limits(request).hit("download", principal)
    return principal


def rate_limits(request: Request) -> RateLimits:
    limits: RateLimits = request.app.state.rate_limits
    return limits


def actor(request: Request, principal: Principal) -> str:
    """Who acts, for events and tombstones: the token's subject. With auth off there is none: the
    name the CLI sends (X-Fleet-User, user@host), else the client's address."""
    if principal.token_id is not None:
        return principal.subject
    user = request.headers.get("x-fleet-user")
    if user:
        return user[:256]
    return f"api@{request.client.host if request.client else 'unknown'}"
