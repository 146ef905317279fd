"""The console's runs table in a real browser: the fixture's runs listed, filters that narrow it,
headers that sort it, cursor pages, errors shown on the page, and URLs that survive a login."""

from __future__ import annotations

from typing import Any

import httpx
import pytest
from selenium import webdriver
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select

from services.console.web import SESSION_COOKIE
from tests.services.console.browser import find, log_in, screenshot, text_of, wait_for
from tests.services.console.conftest import ConsoleDepot

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def rows(chrome: webdriver.Chrome) -> list[dict[str, str]]:
    """The table's rows as their data attributes (run, robot, tier, status, bytes, started)."""
    out = []
    for tr in chrome.find_elements(By.CSS_SELECTOR, "#runs tbody tr"):
        out.append({key: tr.get_attribute(f"data-{key}") or "" for key in ("run", "robot", "tier", "bytes", "started")})
    return out


def api_ids(depot: ConsoleDepot, **params: str) -> list[str]:
    answer = depot.api("GET", "/v1/runs", params={"limit": "1000", **params})
    assert answer.status_code == 200, answer.text
    return [r["id"] for r in answer.json()["runs"]]


def wait_url(chrome: webdriver.Chrome, part: str) -> None:
    wait_for(lambda: part in chrome.current_url, 30, f"the URL to hold {part!r}")


@pytest.fixture
def table(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> webdriver.Chrome:
    log_in(chrome, console_depot.url, console_depot.tokens["read"], then="/console/runs")
    wait_for(lambda: find(chrome, "#runs tbody tr"), 30, "the runs table")
    return chrome


def test_lists_the_fixtures_runs(table: webdriver.Chrome, console_depot: ConsoleDepot):
    listed = rows(table)
    ids = [r["run"] for r in listed]
    assert set(console_depot.runs.values()) <= set(ids)
    assert ids == api_ids(console_depot, limit="50")  # newest first, as GET /v1/runs
    hot = console_depot.runs["hot"]
    row = find(table, f"#runs tr[data-run='{hot}']")
    cells = [td.text for td in row.find_elements(By.CSS_SELECTOR, "td")]
    assert cells[0] == hot and cells[1] == "robot-b" and cells[2] == "fleet-console" and cells[5] == "hot"
    assert cells[3].endswith("UTC") and cells[7].endswith("B") and int(cells[8].replace(",", "")) > 0
    link = row.find_element(By.CSS_SELECTOR, "td a")
    assert link.get_attribute("href") == f"{console_depot.url}/console/runs/{hot}"
    headers = [th.text.rstrip(" ▲▼") for th in table.find_elements(By.CSS_SELECTOR, "#runs thead th")]
    assert headers == [
        "run",
        "robot",
        "application",
        "started",
        "duration",
        "tier",
        "status",
        "size",
        "chunks",
        "pinned",
    ]
    screenshot(table, "runs")


def test_filters_narrow_the_table(table: webdriver.Chrome, console_depot: ConsoleDepot):
    box = find(table, "#run-filters input[name=robot]")
    box.clear()
    box.send_keys("robot-b")
    find(table, "#run-filters button[type=submit]").click()
    wait_url(table, "robot=robot-b")
    listed = wait_for(
        lambda: rows(table) if all(r["robot"] == "robot-b" for r in rows(table)) else None, 30, "robot-b's runs"
    )
    ids = {r["run"] for r in listed}
    assert {console_depot.runs["sealed-b"], console_depot.runs["hot"]} <= ids
    assert console_depot.runs["sealed"] not in ids
    assert ids == set(api_ids(console_depot, robot="robot-b"))

    Select(find(table, "#run-filters select[name=tier]")).select_by_value("hot")
    find(table, "#run-filters button[type=submit]").click()
    wait_url(table, "tier=hot")
    assert "robot=robot-b" in table.current_url  # the robot filter stays
    listed = rows(table)
    assert listed and all(r["tier"] == "hot" and r["robot"] == "robot-b" for r in listed)
    assert console_depot.runs["hot"] in {r["run"] for r in listed}
    assert console_depot.runs["sealed-b"] not in {r["run"] for r in listed}
    # the form shows the filters of the URL it came from
    assert find(table, "#run-filters input[name=robot]").get_attribute("value") == "robot-b"
    assert Select(find(table, "#run-filters select[name=tier]")).first_selected_option.text == "hot"

    table.get(f"{console_depot.url}/console/runs?property=fleet.robot_id=robot-a&entity=/battery/**")
    listed = wait_for(lambda: rows(table), 30, "robot-a's runs by property")
    assert {r["robot"] for r in listed} == {"robot-a"} and console_depot.runs["sealed"] in {r["run"] for r in listed}
    table.get(f"{console_depot.url}/console/runs?entity=/no/such/entity")
    assert "No run matches" in text_of(table, "#no-runs")


def test_headers_sort_the_table(table: webdriver.Chrome, console_depot: ConsoleDepot):
    find(table, "#runs thead a[data-sort=size]").click()
    wait_url(table, "sort=-bytes")
    sizes = [int(r["bytes"]) for r in rows(table)]
    assert len(sizes) >= 3 and sizes == sorted(sizes, reverse=True)
    assert find(table, "#runs thead th[aria-sort]").text.startswith("size")
    find(table, "#runs thead a[data-sort=size]").click()  # again: the other way
    wait_url(table, "sort=bytes")
    assert [int(r["bytes"]) for r in rows(table)] == sorted(sizes)
    find(table, "#runs thead a[data-sort=run]").click()
    wait_url(table, "sort=id")
    ids = [r["run"] for r in rows(table)]
    assert ids == sorted(ids) == api_ids(console_depot, sort="id", limit="50")


def test_pages_through_with_the_cursor(table: webdriver.Chrome, console_depot: ConsoleDepot):
    table.get(f"{console_depot.url}/console/runs?sort=id&limit=1")
    seen: list[str] = []
    expected = api_ids(console_depot, sort="id")
    for _ in range(len(expected)):
        page = rows(table)
        assert len(page) == 1
        seen.append(page[0]["run"])
        nexts = table.find_elements(By.CSS_SELECTOR, "#next-page")
        if not nexts:
            break
        href = nexts[0].get_attribute("href") or ""
        assert "cursor=" in href and "limit=1" in href and "sort=id" in href
        nexts[0].click()
        wait_url(table, href)  # the next page
        assert find(table, "#first-page")
    assert seen == expected
    assert not table.find_elements(By.CSS_SELECTOR, "#next-page")
    find(table, "#first-page").click()
    wait_for(lambda: "cursor=" not in table.current_url, 30, "the first page")
    assert rows(table)[0]["run"] == expected[0]


def test_bad_filters_show_the_error(table: webdriver.Chrome, console_depot: ConsoleDepot):
    table.get(f"{console_depot.url}/console/runs?since=yesterday&robot=robot-a")
    problem = text_of(table, "#problem")
    assert "'since'" in problem and "ISO-8601" in problem and "yesterday" in problem
    assert not table.find_elements(By.CSS_SELECTOR, "#runs")
    assert find(table, "#run-filters input[name=since]").get_attribute("value") == "yesterday"  # to correct it
    cookie = next(c["value"] for c in table.get_cookies() if c["name"] == SESSION_COOKIE)
    for query, name in (
        ("since=yesterday", "since"),
        ("tier=lukewarm", "tier"),
        ("limit=lots", "limit"),
        ("property=x", "property"),
    ):
        answer = httpx.get(
            f"{console_depot.url}/console/runs?{query}", headers={"Cookie": f"{SESSION_COOKIE}={cookie}"}, timeout=30
        )
        assert answer.status_code == 400 and f"parameter &#39;{name}&#39;" in answer.text, (query, answer.status_code)
        assert answer.headers["content-type"].startswith("text/html")


def test_a_shared_link_survives_the_login(chrome: webdriver.Chrome, console_depot: ConsoleDepot):
    shared = "/console/runs?robot=robot-b&tier=hot&sort=id"
    chrome.get(f"{console_depot.url}{shared}")
    wait_url(chrome, "/console/login")
    find(chrome, "input[name=token]").send_keys(console_depot.tokens["read"])
    find(chrome, "form[action='/console/login'] button[type=submit]").click()
    wait_for(lambda: chrome.current_url == f"{console_depot.url}{shared}", 30, "the shared page after logging in")
    listed: list[dict[str, Any]] = rows(chrome)
    assert listed and all(r["robot"] == "robot-b" and r["tier"] == "hot" for r in listed)
