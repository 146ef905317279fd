"""The depot for AI assistants, as an assistant reaches it: the `mcp` client library over stdio
(`fleet mcp`) and over streamable HTTP (`/mcp` on the depot, auth on). A client finds a run hidden
among others by its robot and an event, reads its log lines around the event, and gets a signed
viewer link that opens; write tools refuse a read token; bad arguments are tool errors, never a
crash; no token appears in any answer."""

from __future__ import annotations

import datetime as dt
import json
import os
import sys
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import anyio
import httpx
import pytest
from mcp import ClientSession
from mcp.client.stdio import StdioServerParameters, stdio_client
from mcp.client.streamable_http import streamablehttp_client
from pydantic import AnyUrl

from tests.services.analytics.conftest import log_with_sdk
from tests.services.ingest.live_server import LiveServer
from tests.services.lakehouse.test_outside_engines import SCRIPT

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

FLEET = str(Path(sys.executable).with_name("fleet"))
RUNS = {"mcp-run-1": "robot-1", "mcp-run-2": "robot-2", "mcp-run-3": "robot-2"}
HIDDEN = "mcp-run-2"  # robot-2's run with the event
TOOLS = {
    "find_runs",
    "get_run",
    "list_events",
    "run_logs",
    "scalar_series",
    "sql",
    "viewer_link",
    "tag_run",
    "annotate_run",
    "request_pull",
}


@dataclass(frozen=True)
class Depot:
    server: LiveServer
    read_token: str
    write_token: str
    event_start: str  # the event's start, ISO-8601 (to the microsecond): a log line's time
    lines: list[tuple[int, str]]  # the hidden run's log lines (log_time in ns, text), as SQL reads them


def _token(server: LiveServer, scopes: list[str], name: str) -> str:
    answer = httpx.post(
        f"{server.url}/v1/tokens", json={"scopes": scopes, "name": name}, headers=server.headers, timeout=30
    )
    assert answer.status_code == 201, answer.text
    return str(answer.json()["token"])


@pytest.fixture(scope="module")
def depot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Depot]:
    root = tmp_path_factory.mktemp("mcp")
    folder = root / "sdk"
    folder.mkdir()
    log_with_sdk(f"FOLDER = {str(folder)!r}\n" + SCRIPT.format(runs=json.dumps(RUNS)), flush_rows=8)
    server = LiveServer(root / "data", auth="on", promote_after_s="0", promote_interval_s="0.2").start()
    try:
        for run in RUNS:
            body = (folder / f"{run}.rrd").read_bytes()
            assert httpx.post(f"{server.url}/v1/uploads", content=body, headers=server.headers).status_code == 200

        def sealed() -> bool:
            runs = httpx.get(f"{server.url}/v1/runs", headers=server.headers, timeout=10).json()["runs"]
            return sorted(r["id"] for r in runs if r["tier"] == "warm") == sorted(RUNS)

        server.wait_for(sealed, 120, "every run sealed")
        query = f"SELECT epoch_ns(log_time) AS ns, text FROM text_logs WHERE run_id = '{HIDDEN}' ORDER BY ns"
        rows = httpx.post(f"{server.url}/v1/sql", json={"query": query}, headers=server.headers).json()["rows"]
        lines = [(int(ns), str(text)) for ns, text in rows]
        assert len(lines) >= 5, lines
        at = dt.datetime.fromtimestamp(lines[2][0] // 1000 / 1e6, dt.UTC)  # the 3rd line, to the microsecond
        start = at.isoformat().replace("+00:00", "Z")
        event = {"timeline": "log_time", "start": start, "kind": "bump", "label": "hit the dock", "severity": "warn"}
        marked = httpx.post(f"{server.url}/v1/runs/{HIDDEN}/events", json=event, headers=server.headers)
        assert marked.status_code == 200, marked.text
        read, write = _token(server, ["read"], "assistant-read"), _token(server, ["read", "write"], "assistant-w")
        yield Depot(server, read, write, start, lines)
    finally:
        server.stop()


@asynccontextmanager
async def session(depot: Depot, transport: str, token: str) -> AsyncIterator[ClientSession]:
    if transport == "http":
        headers = {"Authorization": f"Bearer {token}"}
        url = f"{depot.server.url}/mcp"
        async with (
            streamablehttp_client(url, headers=headers) as (read, write, _),
            ClientSession(read, write) as client,
        ):
            await client.initialize()
            yield client
        return
    env = {**os.environ, "FLEET_API_URL": depot.server.url, "FLEET_TOKEN": token}
    params = StdioServerParameters(command=FLEET, args=["mcp"], env=env)
    async with stdio_client(params) as (read, write), ClientSession(read, write) as client:
        await client.initialize()
        yield client


async def call(client: ClientSession, tool: str, **arguments: Any) -> tuple[bool, Any]:
    """(is it an error, its structured answer or its text)."""
    result = await client.call_tool(tool, arguments)
    text = "".join(getattr(c, "text", "") for c in result.content)
    if result.isError:
        return True, text
    return False, result.structuredContent if result.structuredContent is not None else json.loads(text)


@pytest.mark.parametrize("transport", ["http", "stdio"])
def test_an_assistant_finds_the_run_reads_its_logs_and_opens_it(depot: Depot, transport: str) -> None:
    answers: list[str] = []

    async def scenario() -> None:
        async with session(depot, transport, depot.read_token) as client:
            listed = {tool.name for tool in (await client.list_tools()).tools}
            assert listed >= TOOLS, listed
            bad, found = await call(client, "find_runs", robot=["robot-2"], event=["bump"])
            assert not bad, found
            assert [r["id"] for r in found["result"]["runs"]] == [HIDDEN]
            bad, page = await call(client, "find_runs", prop=["fleet.robot_id=robot-2"], tier="warm", limit=1)
            assert not bad and len(page["result"]["runs"]) == 1 and page["result"]["next_cursor"], page
            bad, rest = await call(
                client, "find_runs", prop=["fleet.robot_id=robot-2"], cursor=page["result"]["next_cursor"]
            )
            assert not bad and len(rest["result"]["runs"]) == 1, rest  # robot-2's other run
            bad, events = await call(client, "list_events", kind=["bump"])
            assert not bad and [e["run_id"] for e in events["result"]["events"]] == [HIDDEN], events
            window = 0.0005  # half a millisecond each side of the event
            bad, logs = await call(
                client, "run_logs", run_id=HIDDEN, around=depot.event_start, before_s=window, after_s=window
            )
            assert not bad, logs
            at = round(dt.datetime.fromisoformat(depot.event_start).timestamp() * 1e6) * 1000
            near = [text for ns, text in depot.lines if at - 500_000 <= ns <= at + 500_000]
            assert [row["text"] for row in logs["result"]["rows"]] == near and near, (logs, near)
            bad, run = await call(client, "get_run", run_id=HIDDEN)
            assert not bad and run["result"]["robot_id"] == "robot-2", run
            bad, counted = await call(client, "sql", query="SELECT count(*) AS n FROM runs", max_rows=5)
            assert not bad and counted["result"]["rows"] == [{"n": 3}], counted
            summary = await client.read_resource(AnyUrl(f"fleet://runs/{HIDDEN}"))
            text = "".join(getattr(c, "text", "") for c in summary.contents)
            assert json.loads(text)["result"]["robot_id"] == "robot-2", text
            bad, series = await call(client, "scalar_series", run_id=HIDDEN, entity="/battery", points=10)
            assert not bad and 1 <= len(series["result"]["rows"]) <= 10, series
            bad, link = await call(client, "viewer_link", run_id=HIDDEN, start=depot.event_start)
            assert not bad, link
            opened = httpx.get(link["url"], timeout=60)  # no header: the link is signed
            assert opened.status_code == 200 and opened.content[:4] == b"RRF2", opened.status_code
            writes: tuple[tuple[str, dict[str, Any]], ...] = (
                ("tag_run", {"tags": ["checked"]}),
                ("annotate_run", {"start": depot.event_start, "label": "not mine to add"}),
                ("request_pull", {"start": depot.event_start}),
            )
            for tool, arguments in writes:
                refused, why = await call(client, tool, run_id=HIDDEN, **arguments)
                assert refused and "write" in why.lower(), (tool, why)
            bad_arguments: tuple[tuple[str, dict[str, Any]], ...] = (
                ("get_run", {"run_id": "../../etc/passwd"}),
                ("run_logs", {"run_id": HIDDEN, "around": "yesterday"}),
                ("find_runs", {"limit": 100_000}),
                ("sql", {"query": "DROP TABLE runs"}),
            )
            for tool, arguments in bad_arguments:
                bad, text = await call(client, tool, **arguments)
                assert bad and text, (tool, text)
                answers.append(text)
            answers.extend(json.dumps(a) for a in (found, events, logs, link))
        async with session(depot, transport, depot.write_token) as client:
            bad, tagged = await call(client, "tag_run", run_id=HIDDEN, tags=["checked"])
            assert not bad and "checked" in json.dumps(tagged), tagged
            bad, found = await call(client, "find_runs", tag=["checked"])
            assert not bad and [r["id"] for r in found["result"]["runs"]] == [HIDDEN], found
            bad, note = await call(client, "annotate_run", run_id=HIDDEN, start=depot.event_start, label="checked")
            assert not bad and note["result"]["origin"] == "person", note
            bad, pull = await call(client, "request_pull", run_id=HIDDEN, start=depot.event_start, include=["/logs"])
            assert not bad and pull["result"]["pull"]["run_id"] == HIDDEN, pull

    anyio.run(scenario)
    for text in answers:
        for token in (depot.read_token, depot.write_token):
            assert token not in text


def test_http_without_a_valid_token_is_refused(depot: Depot) -> None:
    body = {"jsonrpc": "2.0", "id": 1, "method": "tools/list"}
    headers = {"Accept": "application/json, text/event-stream"}
    for auth in ({}, {"Authorization": "Bearer not-a-token"}):
        answer = httpx.post(f"{depot.server.url}/mcp", json=body, headers={**headers, **auth}, timeout=30)
        assert answer.status_code == 401 and answer.json()["code"] == "UNAUTHENTICATED", answer.text
