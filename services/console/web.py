"""The console's plumbing: templates, who is logged in, CSRF on every form post, and errors shown as
pages. Page modules declare `router = console_router()` and their handlers take `Viewer` (a logged-in
principal that reads) and, for actions, `Form` (a form post whose CSRF value was checked)."""

from __future__ import annotations

import asyncio
import secrets
from collections.abc import Callable, Coroutine
from importlib import resources
from typing import Annotated, Any
from urllib.parse import quote, urlsplit

from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from fastapi.routing import APIRoute
from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape
from starlette.datastructures import FormData

from core.errors import FleetError, PermissionDeniedError
from services import __version__
from services.auth.scopes import Principal, Scope
from services.auth.sessions import csrf_value, session_principal
from services.auth.tokens import Auth
from services.console import charts, formats

SESSION_COOKIE = "fleet_session"
CSRF_COOKIE = "fleet_csrf"  # a random value for the login form (and every form with auth off)
CSRF_FIELD = "csrf"
CSRF_HEADER = "x-csrf-token"
PREFIX = "/console"

# Scripts only from the depot itself (no inline script); the web viewer's page adds WebAssembly.
CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "connect-src 'self'; frame-ancestors 'none'; base-uri 'self'; form-action 'self'"
)

templates = Environment(
    loader=PackageLoader("services.console", "templates"),
    autoescape=select_autoescape(("html", "svg")),
    undefined=StrictUndefined,  # a misspelt name fails the page's test rather than rendering blank
    trim_blocks=True,
    lstrip_blocks=True,
)
templates.filters.update(formats.FILTERS)
templates.globals.update(charts=charts, quote=quote)


class LoginNeeded(Exception):
    """No valid session: the browser is sent to the login page, and back here after."""


class ConsoleRoute(APIRoute):
    """A console route: an error is shown as a page with its status (not JSON), a missing session
    sends the browser to log in, and every answer carries the console's security headers."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def route(request: Request) -> Response:
            try:
                response = await handler(request)
            except LoginNeeded:
                back = request.url.path + (f"?{request.url.query}" if request.url.query else "")
                response = RedirectResponse(f"{PREFIX}/login?next={quote(back)}", status_code=303)
            except FleetError as exc:  # its page asks the catalog who is logged in: off the event loop
                response = await asyncio.to_thread(error_page, request, exc)
            secure_headers(response)
            return response

        return route


def console_router() -> APIRouter:
    return APIRouter(prefix=PREFIX, route_class=ConsoleRoute, include_in_schema=False)


def secure_headers(response: Response) -> None:
    response.headers.setdefault("content-security-policy", CSP)
    response.headers.setdefault("x-content-type-options", "nosniff")
    response.headers.setdefault("referrer-policy", "same-origin")
    response.headers.setdefault("cache-control", "no-store")


def auth_of(request: Request) -> Auth:
    auth: Auth = request.app.state.auth
    return auth


def logged_in(request: Request) -> Principal | None:
    return session_principal(auth_of(request), request.cookies.get(SESSION_COOKIE))


def viewer(request: Request) -> Principal:
    """The logged-in principal, if it reads; else to the login page."""
    principal = logged_in(request)
    if principal is None or not principal.allows(Scope.READ):
        raise LoginNeeded
    return principal


Viewer = Annotated[Principal, Depends(viewer)]


def csrf_of(request: Request) -> str:
    """The CSRF value this browser's forms carry (see `services.auth.sessions.csrf_value`)."""
    return csrf_value(auth_of(request), request.cookies.get(SESSION_COOKIE), browser_csrf(request))


def browser_csrf(request: Request) -> str:
    """This browser's own random CSRF value (its cookie, or a new one the answer sets)."""
    value = request.cookies.get(CSRF_COOKIE) or getattr(request.state, "new_csrf", None)
    if value is None:
        value = request.state.new_csrf = secrets.token_urlsafe(24)
    return str(value)


async def checked_form(request: Request) -> FormData:
    """The posted form, once its CSRF value (field or htmx header) matches this browser's and it
    came from this depot's own pages; PERMISSION_DENIED otherwise."""
    form = await request.form()
    origin = request.headers.get("origin")
    if origin and origin != "null" and urlsplit(origin).netloc != request.headers.get("host"):
        raise PermissionDeniedError(f"a form posted from another site ({origin}) was refused: use the console itself")
    sent = str(form.get(CSRF_FIELD) or request.headers.get(CSRF_HEADER) or "")
    expected = csrf_of(request)
    if not sent or not secrets.compare_digest(sent, expected):
        raise PermissionDeniedError(
            "this form's CSRF value is missing or stale (the page is older than your login): reload the page and "
            "try again"
        )
    return form


Form = Annotated[FormData, Depends(checked_form)]


def allowed(principal: Principal) -> dict[str, bool]:
    """What the page may offer: actions are shown only to those who may take them."""
    return {scope.value: principal.allows(scope) for scope in Scope}


def render(request: Request, name: str, principal: Principal | None, status: int = 200, **context: Any) -> HTMLResponse:
    """A page: `name` rendered with the console's common context (who is logged in, what they may
    do, the CSRF value for forms)."""
    csrf = csrf_of(request)
    body = templates.get_template(name).render(
        request=request,
        path=request.url.path,
        principal=principal,
        can=allowed(principal) if principal is not None else {},
        csrf=csrf,
        auth_on=auth_of(request).enabled,
        version=__version__,
        prefix=PREFIX,
        **context,
    )
    response = HTMLResponse(body, status_code=status)
    set_browser_csrf(request, response)
    return response


def set_browser_csrf(request: Request, response: Response) -> None:
    if request.cookies.get(CSRF_COOKIE) is None:
        value = browser_csrf(request)
        response.set_cookie(CSRF_COOKIE, value, httponly=True, samesite="strict", secure=is_https(request), path=PREFIX)


def error_page(request: Request, exc: FleetError) -> HTMLResponse:
    principal = logged_in(request)
    return render(request, "error.html", principal, status=exc.http_status(), error=exc)


def is_https(request: Request) -> bool:
    """Whether the browser reached the depot over HTTPS (directly, or through a proxy that says so):
    then cookies are marked Secure."""
    forwarded = request.headers.get("x-forwarded-proto", "")
    return request.url.scheme == "https" or forwarded.split(",")[0].strip() == "https"


def static_dir() -> str:
    return str(resources.files("services.console") / "static")
