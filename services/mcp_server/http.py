"""`/mcp` on the depot: the MCP server over streamable HTTP, for assistants shared by a team.

A request must carry a token of the depot (`Authorization: Bearer`), checked before the MCP SDK
sees it (401 as for REST); its tools then call the depot's own REST app in process with that same
token, so they act with the caller's rights and nothing more. Stateless JSON exchanges: no session
is kept between requests, so any node of a depot answers any request.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from contextvars import ContextVar
from typing import Any

import anyio.to_thread
import httpx
from fastapi import FastAPI
from mcp.server.fastmcp import Context
from starlette.responses import JSONResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send

from core.errors import FleetError
from services.mcp_server.depot import DepotApi
from services.mcp_server.tools import build_server

PATH = "/mcp"
# The Authorization header of the MCP request being answered: the SDK runs a stateless request's
# handlers in tasks started from the request's own (contextvars go with them), where a resource's
# handler has no request object to read it from.
_CALLER: ContextVar[str] = ContextVar("mcp_caller", default="")
SURFACE = "mcp"  # how refusals of its tokens are counted


def install(app: FastAPI) -> AbstractAsyncContextManager[object]:
    """Serve MCP at /mcp on `app`; returns what must run while the app serves (the SDK's session
    manager: `async with install(app): ...`)."""

    @asynccontextmanager
    async def connect(_: Context[Any, Any, Any]) -> AsyncIterator[DepotApi]:
        token = _CALLER.get()  # set by _Authenticated for the request this call came with
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(
            transport=transport, base_url="http://depot", headers={"Authorization": token} if token else {}
        ) as client:
            yield DepotApi(client)

    server = build_server(connect, streamable_http_path=PATH, stateless_http=True, json_response=True)
    mcp_app = server.streamable_http_app()
    for route in mcp_app.routes:
        if isinstance(route, Route) and route.path == PATH:
            app.router.routes.insert(0, Route(PATH, endpoint=_Authenticated(route.endpoint, app), methods=None))
    running: AbstractAsyncContextManager[object] = server.session_manager.run()
    return running


class _Authenticated:
    """The MCP endpoint behind the depot's token check."""

    def __init__(self, inner: ASGIApp, app: FastAPI) -> None:
        self.inner, self.app = inner, app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = dict(scope.get("headers") or [])
        given = headers.get(b"authorization", b"").decode("latin-1")
        token = given[7:].strip() if given[:7].lower() == "bearer " else None
        try:
            await anyio.to_thread.run_sync(self.app.state.auth.authenticate, token, SURFACE)
        except FleetError as exc:
            await JSONResponse(exc.to_dict(), status_code=exc.http_status(), headers=exc.headers())(
                scope, receive, send
            )
            return
        reset = _CALLER.set(f"Bearer {token}" if token else "")
        try:
            await self.inner(scope, receive, send)
        finally:
            _CALLER.reset(reset)
