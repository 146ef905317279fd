"""`/mcp` on the depot: the MCP server over streamable HTTP, for assistants shared by a team.

A request must carry a token of the depot (`Authorization: Bearer`), checked before the MCP SDK
sees it (401 as for REST); its tools then call the depot's own REST app in process with that same
token, so they act with the caller's rights and nothing more. Stateless JSON exchanges: no session
is kept between requests, so any node of a depot answers any request.

The MCP SDK is loaded by the first request to /mcp (in a worker thread), not when the depot starts:
importing it takes about a third of a second, which a depot that no assistant uses never pays.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from contextvars import ContextVar
from typing import TYPE_CHECKING, Any

import anyio
import anyio.abc
import anyio.to_thread
import httpx
from fastapi import FastAPI
from starlette.responses import JSONResponse
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send

from core.errors import FleetError, UnavailableError

if TYPE_CHECKING:
    from mcp.server.fastmcp import Context
    from mcp.server.streamable_http_manager import StreamableHTTPSessionManager

    from services.mcp_server.depot import DepotApi

log = logging.getLogger(__name__)

PATH = "/mcp"
# The Authorization header of the MCP request being answered: the SDK runs a stateless request's
# handlers in tasks started from the request's own (contextvars go with them), where a resource's
# handler has no request object to read it from.
_CALLER: ContextVar[str] = ContextVar("mcp_caller", default="")
SURFACE = "mcp"  # how refusals of its tokens are counted


def install(app: FastAPI) -> AbstractAsyncContextManager[object]:
    """Serve MCP at /mcp on `app`; returns what must run while the app serves (`async with
    install(app): ...`): the SDK's session manager, once a first request has loaded it."""
    endpoint = _OnFirstUse(app)
    app.router.routes.insert(0, Route(PATH, endpoint=_Authenticated(endpoint, app), methods=None))
    return endpoint.running()


def _build(app: FastAPI) -> tuple[ASGIApp, StreamableHTTPSessionManager]:
    """The MCP server whose tools call `app`: its /mcp endpoint and its session manager."""
    from services.mcp_server.depot import DepotApi
    from services.mcp_server.tools import build_server

    @asynccontextmanager
    async def connect(_: Context[Any, Any, Any]) -> AsyncIterator[DepotApi]:
        token = _CALLER.get()  # set by _Authenticated for the request this call came with
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(
            transport=transport, base_url="http://depot", headers={"Authorization": token} if token else {}
        ) as client:
            yield DepotApi(client)

    server = build_server(connect, streamable_http_path=PATH, stateless_http=True, json_response=True)
    for route in server.streamable_http_app().routes:
        if isinstance(route, Route) and route.path == PATH:
            return route.endpoint, server.session_manager
    raise RuntimeError(f"the MCP SDK's app has no {PATH} route")


class _OnFirstUse:
    """The MCP endpoint, built by the first request; its session manager then runs in a task of
    `running()` (an anyio task group is left by the task that entered it) until the depot stops."""

    def __init__(self, app: FastAPI) -> None:
        self.app = app
        self._endpoint: ASGIApp | None = None
        self._failed: str | None = None
        self._lock = anyio.Lock()
        self._tasks: anyio.abc.TaskGroup | None = None
        self._stop = anyio.Event()

    @asynccontextmanager
    async def running(self) -> AsyncIterator[object]:
        async with anyio.create_task_group() as tasks:
            self._tasks = tasks
            try:
                yield self
            finally:
                self._stop.set()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        async with self._lock:
            if self._endpoint is None and self._failed is None:
                await self._start()
        if self._endpoint is None:
            raise UnavailableError(f"the MCP server could not start: {self._failed}")
        await self._endpoint(scope, receive, send)

    async def _start(self) -> None:
        if self._tasks is None:
            raise UnavailableError("the MCP server is not running: the depot is starting or stopping")
        try:
            endpoint, sessions = await anyio.to_thread.run_sync(_build, self.app)
        except Exception as exc:  # the depot serves on; /mcp says what failed
            log.exception("the MCP server could not be built")
            self._failed = f"{type(exc).__name__}: {exc}"
            return
        ready = anyio.Event()

        async def serve() -> None:
            try:
                async with sessions.run():
                    ready.set()
                    await self._stop.wait()
            except Exception as exc:  # the depot serves on; /mcp says what failed
                log.exception("the MCP server stopped")
                self._failed = f"{type(exc).__name__}: {exc}"
                self._endpoint = None  # a manager that stopped answers nothing: 503 from now on
            finally:
                ready.set()

        self._tasks.start_soon(serve)
        await ready.wait()
        if self._failed is None:
            self._endpoint = endpoint


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
