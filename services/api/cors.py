"""Cross-origin requests: the configured web origins (FLEET_CORS_ORIGINS, a console) may call every
endpoint with a token; any other origin may only make simple GETs, with no header of its own, so
a page elsewhere can fetch a recording by signed link (the Rerun web viewer) and nothing more."""

from __future__ import annotations

from starlette.datastructures import Headers
from starlette.middleware.cors import CORSMiddleware
from starlette.types import ASGIApp, Receive, Scope, Send

EXPOSED = ["Content-Disposition", "ETag", "Retry-After", "X-Row-Count"]


class Cors:
    def __init__(self, app: ASGIApp, origins: list[str]) -> None:
        self.origins = frozenset(o.rstrip("/") for o in origins)
        self.configured = CORSMiddleware(
            app,
            allow_origins=sorted(self.origins),
            allow_methods=["GET", "HEAD", "POST", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "Accept"],
            expose_headers=EXPOSED,
        )
        self.public = CORSMiddleware(app, allow_origins=["*"], allow_methods=["GET", "HEAD"], expose_headers=EXPOSED)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and Headers(scope=scope).get("origin") in self.origins:
            await self.configured(scope, receive, send)
        else:
            await self.public(scope, receive, send)
