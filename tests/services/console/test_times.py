"""The console writes every time a person reads as the CLI does (core.timefmt): the run page's
timeline table, coverage range, text-log times and RecordingInfo:start_time, never as raw epoch
nanoseconds or floored seconds; and the depot answers the browser's favicon request."""

from __future__ import annotations

import re

import httpx
import pytest

from core.timefmt import timeline_value
from tests.services.console.conftest import ConsoleDepot

pytestmark = pytest.mark.slow

CSRF = re.compile(r'name="csrf" value="([^"]+)"')
ISO_NS = r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{9}Z"
RAW_EPOCH = re.compile(r"(?<![\d.])\d{10,19}(?![\d.])")  # epoch seconds or nanoseconds as bare numbers


def logged_in(depot: ConsoleDepot, scope: str = "read") -> httpx.Client:
    client = httpx.Client(base_url=depot.url, timeout=60)
    form = client.get("/console/login")
    found = CSRF.search(form.text)
    assert found, form.text[:500]
    form_data = {"token": depot.tokens[scope], "csrf": found.group(1), "next": "/console/"}
    answer = client.post("/console/login", data=form_data)
    assert answer.status_code in (200, 303), answer.text[:500]
    return client


def page_of(depot: ConsoleDepot, path: str) -> httpx.Response:
    client = logged_in(depot)
    try:
        return client.get(path)
    finally:
        client.close()


def section(page: str, name: str) -> str:
    start = page.index(f'id="{name}"')
    return page[start : page.index("</section>", start)]


@pytest.mark.parametrize("role", ["sealed", "hot"])  # plots and logs from the analytics tables, or the run
def test_run_page_writes_times_as_the_cli_does(console_depot: ConsoleDepot, role: str) -> None:
    depot, run_id = console_depot, console_depot.runs[role]
    run = depot.api("GET", f"/v1/runs/{run_id}").json()
    page = page_of(depot, f"/console/runs/{run_id}")
    assert page.status_code == 200, page.text[:500]
    text = page.text

    coverage = section(text, "coverage")
    for t in run["timelines"]:  # the table: each bound as `fleet runs show` prints it
        first = timeline_value(t["type"], t["min"])
        assert f'<td>{t["name"]}</td><td>{t["type"]}</td><td class="num">{first}</td>' in coverage
    assert any(t["type"] == "timestamp" for t in run["timelines"])
    assert re.search(ISO_NS, coverage)

    logs = section(text, "logs")
    times = re.findall(r'<td class="num">([^<]*)</td>', logs)
    assert times and all(re.fullmatch(ISO_NS, t) for t in times), times  # log_time as dates, to the nanosecond

    properties = section(text, "properties")
    start = run["properties"]["recording"]["RecordingInfo:start_time"]
    assert timeline_value("timestamp", start) in properties

    for name, html in (("coverage", coverage), ("logs", logs), ("properties", properties)):
        assert not RAW_EPOCH.search(re.sub(r"<[^>]+>", " ", html)), (name, RAW_EPOCH.findall(html))


def test_favicon_is_served(console_depot: ConsoleDepot) -> None:
    icon = httpx.get(f"{console_depot.url}/favicon.ico", timeout=10)  # no session: browsers ask before logging in
    assert icon.status_code == 200
    assert icon.headers["content-type"].startswith("image/svg+xml")
    assert icon.content.startswith(b"<svg")
    page = page_of(console_depot, "/console/runs").text
    linked = re.search(r'<link rel="icon"[^>]*href="([^"]+)"', page)
    assert linked and httpx.get(f"{console_depot.url}{linked.group(1)}", timeout=10).status_code == 200
