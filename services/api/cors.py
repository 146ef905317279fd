"""Cross-origin requests: the configured web origins (FLEET_CORS_ORIGINS, a console) may call every
endpoint with a token; any other origin may only make simple GETs, with no header of its own, so
a page elsewhere can fetch a recording by signed link (the Rerun web viewer) and nothing more.

A refused preflight carries no Access-Control-Allow-Origin. A write that skips the preflight (a
form, a `no-cors` fetch) from another origin is refused before any route runs: with auth off on
loopback, nothing else would stop a web page in the operator's browser from uploading or pinning."""

from __future__ import annotations

from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.middleware.cors import CORSMiddleware
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from core.errors import PermissionDeniedError

EXPOSED = ["Content-Disposition", "ETag", "Fleet-Warnings", "Retry-After", "X-Row-Count"]
READS = frozenset({"GET", "HEAD"})
_ALLOW_ORIGIN = "access-control-allow-origin"


class Cors:
    def __init__(self, app: ASGIApp, origins: list[str]) -> None:
        self.app = app
        self.origins = frozenset(o.rstrip("/") for o in origins)
        self.configured = CORSMiddleware(
            app,
            allow_origins=sorted(self.origins),
            allow_methods=["GET", "HEAD", "POST", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "Accept"],
            expose_headers=EXPOSED,
        )
        self.public = CORSMiddleware(app, allow_origins=["*"], allow_methods=sorted(READS), expose_headers=EXPOSED)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        origin = headers.get("origin")
        if origin is not None and origin.rstrip("/") in self.origins:
            await self.configured(scope, receive, send)
        elif origin is None or _same_origin(origin, headers.get("host")):
            await self.app(scope, receive, send)  # not cross-origin: CORS has nothing to say
        elif scope["method"] == "OPTIONS" and "access-control-request-method" in headers:
            preflight = self.public.preflight_response(request_headers=headers)
            if preflight.status_code != 200:
                del preflight.headers[_ALLOW_ORIGIN]  # refused: nothing a browser could read as approval
            await preflight(scope, receive, send)
        elif scope["method"] in READS:
            await self.public(scope, receive, send)
        else:
            refused = PermissionDeniedError(
                f"web pages from {origin} may only read here (GET); to let them call the API, "
                "add that origin to FLEET_CORS_ORIGINS"
            )
            await JSONResponse(refused.to_dict(), refused.http_status())(scope, receive, send)


def _same_origin(origin: str, host: str | None) -> bool:
    """A request from the depot's own pages (Swagger UI at /docs): its origin names the host it came to."""
    return host is not None and urlsplit(origin).netloc.lower() == host.lower()
