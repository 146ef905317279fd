"""A real `fleet serve` (auth on, embedded catalog) holding runs logged with the real rerun-sdk,
and a headless Chromium: what the console's tests look at. Both live for the whole session; tests
that change a run (pin, delete) use runs of their own (`ConsoleDepot.new_run`)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
from selenium import webdriver

from tests.services.analytics.conftest import log_with_sdk
from tests.services.console.browser import forget_session, start_chrome
from tests.services.ingest.live_server import LiveServer

# Two robots, each run with a battery that drains (scalars), text logs, points and a recording
# property: what the console's pages show. `frame` counts 0..N-1; log_time is the wall clock.
SCRIPT = """
rec = rr.RecordingStream("fleet-console", recording_id=run_id)
rec.save(out)
rec.send_property("fleet", rr.AnyValues(robot_id=robot, site="lab-2"))
for frame in range(60):
    rec.set_time("frame", sequence=frame)
    rec.log("/battery/voltage", rr.Scalars(24.0 - drain * frame))
    rec.log("/world/points", rr.Points3D(np.random.default_rng(frame).random((20, 3))))
    if frame % 10 == 0:
        rec.log("/logs", rr.TextLog(f"frame {frame}: all good", level="INFO"))
rec.log("/logs", rr.TextLog("battery low", level="WARN"))
finish(rec)
"""


@dataclass
class ConsoleDepot:
    server: LiveServer
    root: Path
    tokens: dict[str, str] = field(default_factory=dict)  # scope -> a token with that scope only
    runs: dict[str, str] = field(default_factory=dict)  # role ("sealed", "hot", ...) -> run id

    @property
    def url(self) -> str:
        return self.server.url

    @property
    def admin(self) -> str:
        return (self.server.data_dir / "admin.token").read_text().strip()

    def api(self, method: str, path: str, token: str | None = None, **kwargs: Any) -> httpx.Response:
        headers = {"Authorization": f"Bearer {token or self.admin}"}
        return httpx.request(method, f"{self.url}{path}", headers=headers, timeout=60, **kwargs)

    def token(self, *scopes: str, robot: str | None = None) -> str:
        body: dict[str, Any] = {"scopes": list(scopes), "name": f"console test {' '.join(scopes)}"}
        if robot:
            body["robot"] = robot
        answer = self.api("POST", "/v1/tokens", json=body)
        assert answer.status_code == 201, answer.text
        return str(answer.json()["token"])

    def new_run(self, robot: str = "robot-a", *, sealed: bool = True, drain: float = 0.05) -> str:
        """A run logged with the real SDK, uploaded, and sealed (promoted) unless `sealed` is False."""
        run_id = f"console-{uuid.uuid4().hex[:10]}"
        path = self.root / f"{run_id}.rrd"
        log_with_sdk(f"out, run_id, robot, drain = {str(path)!r}, {run_id!r}, {robot!r}, {drain!r}\n" + SCRIPT)
        answer = self.api("POST", "/v1/uploads", content=path.read_bytes())
        assert answer.status_code in (200, 201, 202), answer.text
        if sealed:
            answer = self.api("POST", f"/v1/runs/{run_id}/promote")
            assert answer.status_code == 200, answer.text
        return run_id


@pytest.fixture(scope="session")
def console_depot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleDepot]:
    root = tmp_path_factory.mktemp("console")
    server = LiveServer(root / "data", auth="on", auth_cache_s="0", scheduler="false").start()
    depot = ConsoleDepot(server, root)
    try:
        for scope in ("read", "write", "admin"):
            depot.tokens[scope] = depot.token(scope)
        depot.tokens["ingest"] = depot.token("ingest", robot="robot-a")
        depot.runs["sealed"] = depot.new_run("robot-a", drain=0.05)
        depot.runs["sealed-b"] = depot.new_run("robot-b", drain=0.08)
        depot.runs["hot"] = depot.new_run("robot-b", sealed=False)
        yield depot
    finally:
        server.stop()


@pytest.fixture(scope="session")
def chrome_session(tmp_path_factory: pytest.TempPathFactory) -> Iterator[webdriver.Chrome]:
    chrome = start_chrome(tmp_path_factory.mktemp("downloads"))
    try:
        yield chrome
    finally:
        chrome.quit()


@pytest.fixture
def chrome(chrome_session: webdriver.Chrome, console_depot: ConsoleDepot) -> webdriver.Chrome:
    """The session's browser, logged out: no cookie of the depot left from an earlier test."""
    forget_session(chrome_session, console_depot.url)
    return chrome_session
