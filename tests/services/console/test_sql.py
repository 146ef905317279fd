"""The SQL page and the dashboards in a real browser, over a real depot holding SDK runs: answers as
tables and charts, downloads, errors, and saved queries drawn again as runs are sealed."""

from __future__ import annotations

import csv
import io
from collections import Counter
from urllib.parse import urlencode

import httpx
import pytest
from selenium import webdriver
from selenium.common.exceptions import StaleElementReferenceException
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webelement import WebElement
from selenium.webdriver.support.ui import Select

from tests.services.console.browser import find, log_in, log_out, screenshot, text_of, wait_for
from tests.services.console.conftest import ConsoleDepot

pytestmark = [pytest.mark.browser, pytest.mark.slow]

RUNS_PER_ROBOT = (
    "SELECT robot_id, count(*) AS runs FROM runs WHERE tier != 'deleted' GROUP BY robot_id ORDER BY robot_id"
)
# Volts each robot's battery lost, over all its runs (each run: its highest minus its lowest reading).
BATTERY_PER_ROBOT = """SELECT robot_id, sum(drain) AS drain_volts FROM (
  SELECT robot_id, run_id, max(value) - min(value) AS drain FROM scalars
  WHERE entity = '/battery/voltage' GROUP BY robot_id, run_id
) GROUP BY robot_id ORDER BY robot_id"""
FRAMES = 60  # what each run of the console depot logs (tests/services/console/conftest.py)


def _session(chrome: webdriver.Chrome) -> httpx.Client:
    """An HTTP client holding the browser's cookies: what the browser would send."""
    cookies = "; ".join(f"{c['name']}={c['value']}" for c in chrome.get_cookies())
    return httpx.Client(headers={"cookie": cookies}, timeout=60)


def _gone(element: WebElement) -> bool:
    try:
        element.tag_name  # noqa: B018 - asks the browser whether the element is still there
    except StaleElementReferenceException:
        return True
    return False


def _run_query(chrome: webdriver.Chrome, query: str) -> None:
    """Type `query` in the box, run it, and wait for the new page with its answer or its problem."""
    page = find(chrome, "html")
    box = find(chrome, "textarea[name=q]")
    box.clear()
    box.send_keys(query)
    find(chrome, "form.sql-box button[type=submit]").click()
    wait_for(lambda: _gone(page), 60, "the query's page to load")
    wait_for(lambda: chrome.find_elements(By.CSS_SELECTOR, "#sql-rows, #sql-problem"), 60, "the answer of the query")


def _rows(chrome: webdriver.Chrome, css: str = "#sql-rows") -> list[list[str]]:
    return [
        [td.text for td in tr.find_elements(By.CSS_SELECTOR, "td")]
        for tr in chrome.find_elements(By.CSS_SELECTOR, f"{css} tbody tr")
    ]


def _bars(chrome: webdriver.Chrome, css: str) -> dict[str, float]:
    return {
        str(rect.get_attribute("data-label")): float(str(rect.get_attribute("data-value")))
        for rect in chrome.find_elements(By.CSS_SELECTOR, f"{css} svg.chart rect[data-label]")
    }


def test_sql_page_answers_as_a_table_a_chart_and_downloads(chrome: webdriver.Chrome, console_depot: ConsoleDepot):
    depot = console_depot
    log_in(chrome, depot.url, depot.tokens["read"], then="/console/sql")
    assert (
        "battery" in str(find(chrome, "textarea[name=q]").get_attribute("value")).lower()
    )  # the example to start from
    tables = text_of(chrome, "#sql-tables")
    assert all(name in tables for name in ("runs", "robots", "scalars", "text_logs"))

    _run_query(chrome, RUNS_PER_ROBOT)
    shown = {robot: int(count) for robot, count in _rows(chrome)}
    listed = depot.api("GET", "/v1/runs?limit=1000", depot.tokens["read"]).json()["runs"]
    assert shown == dict(Counter(r["robot_id"] for r in listed))
    assert {"robot-a", "robot-b"} <= set(shown)
    assert _bars(chrome, "#sql-chart") == {robot: float(n) for robot, n in shown.items()}  # text x: bars

    # The answer's link runs it again; its CSV download holds the same rows.
    with _session(chrome) as http:
        download = http.get(str(find(chrome, "#download-csv").get_attribute("href")))
        assert download.status_code == 200, download.text
        assert download.headers["content-type"].startswith("text/csv")
        assert download.headers["content-disposition"] == 'attachment; filename="query.csv"'
        rows = list(csv.reader(io.StringIO(download.text)))
        assert rows[0] == ["robot_id", "runs"] and {r: int(n) for r, n in rows[1:]} == shown
        parquet = http.get(str(find(chrome, "#download-parquet").get_attribute("href")))
        assert parquet.status_code == 200 and parquet.content[:4] == b"PAR1"

    # Two numeric columns: a line of one point per frame.
    run = depot.runs["sealed"]
    _run_query(
        chrome,
        f"SELECT frame, value FROM scalars WHERE run_id = '{run}' AND entity = '/battery/voltage' ORDER BY frame",
    )
    assert find(chrome, "#row-count").get_attribute("data-rows") == str(FRAMES)
    line = find(chrome, "#sql-chart svg.chart polyline")
    assert line.get_attribute("data-points") == str(FRAMES)
    screenshot(chrome, "sql")

    # A bad query: its message on the page, with the status 400.
    _run_query(chrome, "SELEC robot_id FROM runs")
    problem = text_of(chrome, "#sql-problem")
    assert "400" in problem and "INVALID_SQL" in problem
    assert find(chrome, "textarea[name=q]").get_attribute("value") == "SELEC robot_id FROM runs"  # kept to fix
    with _session(chrome) as http:
        answer = http.get(f"{depot.url}/console/sql?{urlencode({'q': 'SELEC robot_id FROM runs'})}")
        assert answer.status_code == 400 and "INVALID_SQL" in answer.text
        refused = http.get(f"{depot.url}/console/sql?{urlencode({'q': 'SELECT * FROM duckdb_settings()'})}")
        assert refused.status_code == 400 and "SQL_NOT_ALLOWED" in refused.text

    # A read token may not save: no form, and a crafted post (with a valid CSRF value) is refused.
    _run_query(chrome, RUNS_PER_ROBOT)
    assert not chrome.find_elements(By.CSS_SELECTOR, "#save-form")
    csrf = find(chrome, "form[action='/console/logout'] input[name=csrf]").get_attribute("value")
    with _session(chrome) as http:
        crafted = http.post(
            f"{depot.url}/console/sql/save", data={"csrf": csrf, "q": RUNS_PER_ROBOT, "name": "sneaky", "chart": "bar"}
        )
        assert crafted.status_code == 403, crafted.text
        assert "PERMISSION_DENIED" in crafted.text
    chrome.get(f"{depot.url}/console/dashboards")
    wait_for(lambda: find(chrome, "main h1"), 30, "the dashboards page")
    assert not chrome.find_elements(By.CSS_SELECTOR, "section.dashboard[data-name='sneaky']")


def test_saved_query_is_a_dashboard_chart_that_follows_new_runs(chrome: webdriver.Chrome, console_depot: ConsoleDepot):
    depot = console_depot
    log_in(chrome, depot.url, depot.tokens["write"], then="/console/sql")
    _run_query(chrome, BATTERY_PER_ROBOT)
    before_sql = {robot: float(v) for robot, v in _rows(chrome)}
    assert {"robot-a", "robot-b"} <= set(before_sql)

    find(chrome, "#save-form input[name=name]").send_keys("battery per robot")
    Select(find(chrome, "#save-form select[name=chart]")).select_by_value("bar")
    find(chrome, "#save-form button[type=submit]").click()
    wait_for(lambda: "/console/dashboards" in chrome.current_url, 60, "the dashboards after saving")
    card = "section.dashboard[data-name='battery per robot']"
    before = wait_for(lambda: _bars(chrome, card), 60, "the saved query's bars")
    assert before == pytest.approx(before_sql)
    screenshot(chrome, "dashboards")

    # The name is taken now: saving again says so, and nothing is added.
    chrome.get(f"{depot.url}/console/sql?{urlencode({'q': 'SELECT 1 AS one'})}")
    find(chrome, "#save-form input[name=name]").send_keys("battery per robot")
    find(chrome, "#save-form button[type=submit]").click()
    assert "already named 'battery per robot'" in wait_for(
        lambda: text_of(chrome, "#save-problem"), 60, "the name-taken message"
    )

    # A run sealed since: the dashboard's numbers follow at the next look.
    drained = 0.05 * (FRAMES - 1)
    depot.new_run("robot-a", drain=0.05)
    chrome.get(f"{depot.url}/console/dashboards")
    after = wait_for(lambda: _bars(chrome, card), 60, "the saved query's bars again")
    assert len(chrome.find_elements(By.CSS_SELECTOR, card)) == 1  # saved once, under its name
    assert after["robot-a"] == pytest.approx(before["robot-a"] + drained, abs=1e-6)
    assert after["robot-b"] == pytest.approx(before["robot-b"])
    query_id = find(chrome, card).get_attribute("id")
    with _session(chrome) as http:  # the chart alone, as the page refreshes it every minute
        partial = http.get(f"{depot.url}/console/dashboards/{query_id}/chart")
        assert partial.status_code == 200 and f'id="chart-{query_id}"' in partial.text
        assert "<html" not in partial.text

    # A read token sees the chart, but no delete, and its crafted delete is refused.
    log_out(chrome)
    log_in(chrome, depot.url, depot.tokens["read"], then="/console/dashboards")
    assert _bars(chrome, card) == pytest.approx(after)
    assert not chrome.find_elements(By.CSS_SELECTOR, f"{card} form[action$='/delete']")
    csrf = find(chrome, "form[action='/console/logout'] input[name=csrf]").get_attribute("value")
    with _session(chrome) as http:
        crafted = http.post(f"{depot.url}/console/dashboards/{query_id}/delete", data={"csrf": csrf})
        assert crafted.status_code == 403, crafted.text
    log_out(chrome)

    # The write token deletes it (after confirming).
    log_in(chrome, depot.url, depot.tokens["write"], then="/console/dashboards")
    find(chrome, f"{card} form[action$='/delete'] button").click()
    wait_for(lambda: chrome.switch_to.alert, 10, "the confirmation").accept()
    wait_for(lambda: not chrome.find_elements(By.CSS_SELECTOR, card), 60, "the deleted query to be gone")
