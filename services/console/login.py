"""Logging in and out of the console: a token typed once becomes a session cookie (HttpOnly,
SameSite=Lax, Secure over HTTPS); the token itself is kept nowhere."""

from __future__ import annotations

import asyncio
from typing import Annotated

from fastapi import Query, Request
from fastapi.responses import RedirectResponse, Response

from core.errors import FleetError
from services.auth.sessions import SESSION_TTL, close_session, open_session
from services.console.web import (
    PREFIX,
    SESSION_COOKIE,
    Form,
    auth_of,
    console_router,
    is_https,
    logged_in,
    render,
)

router = console_router()


def safe_next(target: str | None) -> str:
    """Where to go after logging in: a console page of this depot, never another site."""
    if not target or not target.startswith(PREFIX + "/") or target.startswith("//") or "\\" in target:
        return f"{PREFIX}/"
    return target


@router.get("/login")
def login_page(request: Request, next: Annotated[str | None, Query()] = None) -> Response:
    if not auth_of(request).enabled or logged_in(request) is not None:
        return RedirectResponse(safe_next(next), status_code=303)
    return render(request, "login.html", None, next=safe_next(next), problem=None)


@router.post("/login")
async def login(request: Request, form: Form) -> Response:
    token = str(form.get("token") or "")
    target = safe_next(str(form.get("next") or ""))
    try:
        cookie, _ = await asyncio.to_thread(open_session, auth_of(request), token)
    except FleetError as exc:
        return render(request, "login.html", None, status=exc.http_status(), next=target, problem=exc.message)
    response = RedirectResponse(target, status_code=303)
    if cookie is not None:
        response.set_cookie(
            SESSION_COOKIE,
            cookie,
            max_age=int(SESSION_TTL.total_seconds()),
            httponly=True,
            samesite="lax",
            secure=is_https(request),
            path=PREFIX,
        )
    return response


@router.post("/logout")
def logout(request: Request, _: Form) -> Response:
    """The session ends on the depot (its cookie, wherever a copy of it is, is refused from now on),
    and the browser forgets its cookie."""
    close_session(auth_of(request), request.cookies.get(SESSION_COOKIE))
    response = RedirectResponse(f"{PREFIX}/login", status_code=303)
    response.delete_cookie(SESSION_COOKIE, path=PREFIX, httponly=True, samesite="lax", secure=is_https(request))
    return response
