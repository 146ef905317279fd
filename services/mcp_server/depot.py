"""How the MCP tools reach the depot: its REST API, with the caller's token and nothing more.

Each tool is a thin call of a REST route (which is a thin call of the service functions): the
depot checks the token's scopes, limits and rate limits as it does for any client, and a refusal
comes back as the tool's error. Over stdio (`fleet mcp`) the API is the depot's URL; on the depot
itself (`/mcp`) it is the depot's own app, called in process with the token the MCP request
carried. Answers are bounded: lists are cut and every answer stays under MAX_ANSWER_BYTES, saying
so when it was cut.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import httpx
from mcp.server.fastmcp.exceptions import ToolError

MAX_ANSWER_BYTES = 64 * 1024  # what a model reads of one answer at most
MAX_ITEMS = 100  # list items in one answer at most
TIMEOUT_S = 60.0


@dataclass(frozen=True)
class DepotApi:
    """The depot's REST API as one caller reaches it."""

    client: httpx.AsyncClient  # its base URL the depot's, its headers the caller's token

    async def call(self, method: str, path: str, *, params: Mapping[str, Any] | None = None, body: Any = None) -> Any:
        """The route's JSON answer; a refusal (4xx, 5xx) as a ToolError with the depot's own message."""
        query = {k: v for k, v in (params or {}).items() if v is not None and v != [] and v != ""}
        try:
            response = await self.client.request(method, path, params=query, json=body, timeout=TIMEOUT_S)
        except httpx.HTTPError as exc:
            raise ToolError(f"the depot did not answer ({type(exc).__name__}): try again shortly") from None
        if response.status_code >= 400:
            raise ToolError(_refusal(response))
        return response.json()


def _refusal(response: httpx.Response) -> str:
    try:
        body = response.json()
    except ValueError:
        return f"the depot answered {response.status_code}"
    if isinstance(body, dict) and "message" in body:
        return f"{body.get('code', response.status_code)}: {body['message']}"
    return f"the depot answered {response.status_code}"


def bounded(answer: Any, max_items: int = MAX_ITEMS, max_bytes: int = MAX_ANSWER_BYTES) -> dict[str, Any]:
    """`answer` with its lists cut to `max_items` and the whole under `max_bytes` of JSON, wrapped as
    {"result": ..., "truncated": bool, "note": why, if cut}."""
    notes: list[str] = []
    cut = _cut_lists(answer, max_items, notes)
    text = json.dumps(cut, default=str)
    if len(text) > max_bytes:
        cut = _shrink(cut, max_bytes)
        notes.append(f"the answer was over {max_bytes:,} bytes of JSON: items were left out to fit")
    out: dict[str, Any] = {"result": cut, "truncated": bool(notes)}
    if notes:
        out["note"] = "; ".join(dict.fromkeys(notes))
    return out


def _cut_lists(value: Any, max_items: int, notes: list[str]) -> Any:
    if isinstance(value, list):
        if len(value) > max_items:
            notes.append(f"a list of {len(value):,} items was cut to its first {max_items}")
            value = value[:max_items]
        return [_cut_lists(v, max_items, notes) for v in value]
    if isinstance(value, dict):
        return {k: _cut_lists(v, max_items, notes) for k, v in value.items()}
    return value


def _shrink(value: Any, max_bytes: int) -> Any:
    """The longest lists halved until the JSON fits (a long text is cut last)."""
    for _ in range(64):
        if len(json.dumps(value, default=str)) <= max_bytes:
            return value
        if not _halve_longest_list(value):
            break
    text = json.dumps(value, default=str)
    return text[: max_bytes - 100] + "... (cut)" if len(text) > max_bytes else value


def _halve_longest_list(value: Any) -> bool:
    longest: list[Any] | None = None
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, list):
            if len(item) > 1 and (longest is None or len(item) > len(longest)):
                longest = item
            stack.extend(item)
        elif isinstance(item, dict):
            stack.extend(item.values())
    if longest is None:
        return False
    del longest[len(longest) // 2 :]
    return True
