"""/mcp's endpoint built on first use: an MCP server that cannot be built is named in each answer
(503), and the depot serves on."""

from __future__ import annotations

import asyncio

import pytest
from fastapi import FastAPI

from core.errors import UnavailableError
from services.mcp_server import http


def test_an_mcp_server_that_cannot_be_built_is_named_and_the_depot_serves_on(monkeypatch: pytest.MonkeyPatch) -> None:
    builds: list[int] = []

    def broken(app: FastAPI) -> object:
        builds.append(1)
        raise RuntimeError("no such SDK")

    monkeypatch.setattr(http, "_build", broken)
    endpoint = http._OnFirstUse(FastAPI())

    async def ask() -> None:
        async def receive() -> dict[str, object]:
            return {"type": "http.request", "body": b"", "more_body": False}

        async def send(_: object) -> None:
            raise AssertionError("nothing is sent by an endpoint that could not start")

        await endpoint({"type": "http", "method": "POST", "path": "/mcp", "headers": []}, receive, send)

    async def scenario() -> None:
        async with endpoint.running():
            for _ in range(2):
                with pytest.raises(UnavailableError, match=r"could not start: RuntimeError: no such SDK"):
                    await ask()

    asyncio.run(scenario())
    assert builds == [1]  # tried once: the next requests are told the same without trying again


def test_before_the_depot_serves_mcp_is_unavailable() -> None:
    endpoint = http._OnFirstUse(FastAPI())

    async def ask() -> None:
        async def nothing() -> dict[str, object]:
            return {}

        async def ignore(_: object) -> None:
            return None

        await endpoint({"type": "http"}, nothing, ignore)

    with pytest.raises(UnavailableError, match="not running"):
        asyncio.run(ask())
