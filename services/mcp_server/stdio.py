"""`fleet mcp`: the MCP server over stdio, for an assistant on the engineer's machine. Its tools call
the depot's REST API at FLEET_API_URL with the engineer's token (FLEET_TOKEN), as the CLI does."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import httpx
from mcp.server.fastmcp import Context

from services.mcp_server.depot import TIMEOUT_S, DepotApi
from services.mcp_server.tools import build_server


async def serve_stdio(api_url: str, token: str | None) -> None:
    """Answer MCP on stdin/stdout until the assistant closes them."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    async with httpx.AsyncClient(base_url=api_url.rstrip("/"), headers=headers, timeout=TIMEOUT_S) as client:

        @asynccontextmanager
        async def connect(_: Context[Any, Any, Any]) -> AsyncIterator[DepotApi]:
            yield DepotApi(client)

        await build_server(connect).run_stdio_async()
