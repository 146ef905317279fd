"""What a running Rerun viewer shows on screen, as text: its widget tree, read through
`rerun viewer-mcp`, the MCP server (JSON-RPC over stdio) that Rerun ships for driving a viewer.

The viewer-control API (`rerun.experimental.ViewerClient`) reports what is open and loaded, but not
what a table shows: the rows of a dataset's segment table, or the entries the server page lists,
are only on screen. The MCP server's `widget_tree` tool reads them from the viewer's accessibility
tree (labels and values of every visible widget), so a test can wait for them without reading pixels.
"""

from __future__ import annotations

import itertools
import json
import queue
import subprocess
import threading
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

MCP_PROTOCOL = "2025-06-18"
TREE_LIMIT = 5000  # widgets per read: a whole viewer window holds a few hundred


class WidgetsError(AssertionError):
    """The MCP server failed, answered an error, or did not answer in time."""


@dataclass(frozen=True)
class Widget:
    id: str
    role: str | None
    text: str  # its label, else its value ("" for neither)
    panes: tuple[str, ...]  # the labels of the panes it sits in, outermost first


class ViewerWidgets:
    """A `rerun viewer-mcp --endpoint` process attached to one viewer, and the tools it offers."""

    def __init__(self, rerun_exe: str, endpoint: str, *, env: Mapping[str, str], log: Path) -> None:
        self.argv = [rerun_exe, "viewer-mcp", "--endpoint", endpoint]
        self.env = dict(env)
        self.log = log
        self._proc: subprocess.Popen[str] | None = None
        self._answers: queue.Queue[dict[str, Any] | None] = queue.Queue()
        self._next_id = 0

    def start(self, timeout: float = 30) -> ViewerWidgets:
        with open(self.log, "ab") as log:
            self._proc = subprocess.Popen(
                self.argv,
                env=self.env,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=log,
                text=True,
                start_new_session=True,  # a Ctrl-C of the test run stops it through the harness, not twice
            )
        assert self._proc.stdout is not None
        threading.Thread(target=self._read, args=(self._proc.stdout,), daemon=True).start()
        self._request(
            "initialize", {"protocolVersion": MCP_PROTOCOL, "capabilities": {}, "clientInfo": _CLIENT}, timeout
        )
        self._send({"jsonrpc": "2.0", "method": "notifications/initialized"})
        return self

    def stop(self) -> None:
        if self._proc is None or self._proc.poll() is not None:
            return
        assert self._proc.stdin is not None
        self._proc.stdin.close()  # an MCP server over stdio ends with its input
        try:
            self._proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(timeout=10)

    def call(self, tool: str, timeout: float = 30, **arguments: Any) -> dict[str, Any]:
        """One tool call's structured answer; WidgetsError if the tool reports an error."""
        result = self._request("tools/call", {"name": tool, "arguments": arguments}, timeout)
        if result.get("isError"):
            said = " ".join(part.get("text", "") for part in result.get("content", []))
            raise WidgetsError(f"viewer-mcp {tool} failed: {said[:2000]}")
        structured: dict[str, Any] = result.get("structuredContent") or {}
        return structured

    def widgets(self) -> list[Widget]:
        """Every visible widget that says something, depth first."""
        tree = self.call("widget_tree", limit=TREE_LIMIT)
        return list(_flatten(tree.get("nodes", []), ()))

    def texts(self, pane: str | None = None) -> list[str]:
        """The texts of the visible widgets, in screen-tree order; only those inside the pane
        labelled `pane` (e.g. "Entry page", the viewer's main page) if given."""
        return [w.text for w in self.widgets() if w.text and (pane is None or pane in w.panes)]

    # --- JSON-RPC over the process's stdin and stdout -----------------------------------------------

    def _request(self, method: str, params: dict[str, Any], timeout: float) -> dict[str, Any]:
        self._next_id += 1
        ident = self._next_id
        self._send({"jsonrpc": "2.0", "id": ident, "method": method, "params": params})
        deadline = time.monotonic() + timeout
        while True:
            try:
                message = self._answers.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                raise WidgetsError(f"viewer-mcp did not answer {method} within {timeout:g} s") from None
            if message is None:
                raise WidgetsError(f"viewer-mcp exited while answering {method}: see {self.log}")
            if message.get("id") != ident:
                continue  # a notification, or the late answer of a call that timed out
            if "error" in message:
                raise WidgetsError(f"viewer-mcp refused {method}: {message['error']}")
            answer: dict[str, Any] = message.get("result", {})
            return answer

    def _send(self, message: dict[str, Any]) -> None:
        if self._proc is None or self._proc.stdin is None or self._proc.poll() is not None:
            raise WidgetsError(f"viewer-mcp is not running: see {self.log}")
        self._proc.stdin.write(json.dumps(message) + "\n")
        self._proc.stdin.flush()

    def _read(self, stdout: TextIO) -> None:
        """Reader thread: every message the server writes, then None when its output ends."""
        for line in stdout:
            try:
                self._answers.put(json.loads(line))
            except json.JSONDecodeError:
                continue  # not a protocol line
        self._answers.put(None)


_CLIENT = {"name": "fleet-tests", "version": "1"}


def _flatten(nodes: list[dict[str, Any]], panes: tuple[str, ...]) -> Iterator[Widget]:
    for node in nodes:
        role = node.get("role")
        text = node.get("label") or node.get("value") or ""
        yield Widget(node.get("id", ""), role, text, panes)
        inner = (*panes, text) if role == "Pane" and text else panes
        yield from _flatten(node.get("children", []), inner)


def shown_after(texts: list[str], label: str) -> str | None:
    """The text shown right after `label` (a value beside its name), or None if `label` is not shown."""
    return next((value for name, value in itertools.pairwise(texts) if name == label), None)


def table_rows(texts: list[str]) -> int | None:
    """The row count a table's footer shows ("rows", "N"), or None if no table footer is shown."""
    count = shown_after(texts, "rows")
    return int(count) if count is not None and count.isdigit() else None
