"""The console's overview in a real browser, over a depot holding runs logged with the real SDK:
robots and their last runs, runs per day, data by tier as `GET /v1/runs` adds it up, storage, live
and hot runs, retention events."""

from __future__ import annotations

import datetime as dt
import re
from pathlib import Path
from typing import Any

import pytest
from selenium import webdriver
from selenium.webdriver.common.by import By
from sqlalchemy.orm import sessionmaker

from catalog import queries
from catalog.db import create_engine, session_scope
from catalog.queries import RunRecord
from services import __version__
from services.auth.scopes import local_principal
from services.console.web import PREFIX, templates
from services.runs import fleet
from tests.catalog.records import run_record
from tests.services.console.browser import find, log_in, screenshot, text_of, wait_for
from tests.services.console.conftest import ConsoleDepot
from tests.services.nodes import node_of


def all_runs(depot: ConsoleDepot, **params: str) -> list[dict[str, Any]]:
    """Every run `GET /v1/runs` lists with these filters, page after page."""
    runs: list[dict[str, Any]] = []
    cursor = None
    while True:
        answer = depot.api(
            "GET", "/v1/runs", params={**params, "limit": "1000", **({"cursor": cursor} if cursor else {})}
        )
        assert answer.status_code == 200, answer.text
        body = answer.json()
        runs += body["runs"]
        cursor = body["next_cursor"]
        if cursor is None:
            return runs


@pytest.fixture
def overview(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> webdriver.Chrome:
    log_in(chrome, console_depot.url, console_depot.tokens["read"])
    wait_for(lambda: find(chrome, "#robots"), 30, "the overview's robots")
    return chrome


@pytest.mark.browser
@pytest.mark.slow
def test_robots_and_their_last_runs(overview: webdriver.Chrome, console_depot: ConsoleDepot):
    for robot in ("robot-a", "robot-b"):
        newest = all_runs(console_depot, robot=robot)[0]  # newest first, as the overview takes it
        row = find(overview, f"#robots tr[data-robot='{robot}']")
        link = row.find_element(By.CSS_SELECTOR, "td.last-run a")
        assert link.text == newest["id"]
        assert link.get_attribute("href") == f"{console_depot.url}/console/runs/{newest['id']}"
        count = len(all_runs(console_depot, robot=robot))
        assert row.find_elements(By.CSS_SELECTOR, "td.num")[0].text == str(count)
        # runs per day: every run of the fixture started today, so the robot's row adds up to its count
        days = overview.find_elements(By.CSS_SELECTOR, f"#per-day tr[data-robot='{robot}'] td.day")
        assert len(days) == 14 and sum(int(d.get_attribute("data-count") or 0) for d in days) == count
        assert days[-1].get_attribute("data-count") == str(count)
    chart = find(overview, "#per-day svg.chart")
    assert {bar.get_attribute("data-label") for bar in chart.find_elements(By.CSS_SELECTOR, "rect")} >= {
        "robot-a",
        "robot-b",
    }


@pytest.mark.browser
@pytest.mark.slow
def test_data_by_tier_matches_the_runs_api(overview: webdriver.Chrome, console_depot: ConsoleDepot):
    for tier in ("hot", "warm", "cold"):
        runs = all_runs(console_depot, tier=tier)
        row = find(overview, f"#tiers tr[data-tier='{tier}']")
        assert row.get_attribute("data-runs") == str(len(runs)), tier
        assert row.get_attribute("data-bytes") == str(sum(r["bytes"] for r in runs)), tier
        assert row.find_elements(By.CSS_SELECTOR, "td")[1].text == str(len(runs))
    assert int(find(overview, "#tiers tr[data-tier='warm']").get_attribute("data-runs") or 0) >= 2
    assert int(find(overview, "#tiers tr[data-tier='hot']").get_attribute("data-runs") or 0) >= 1
    # the sealed runs' objects are in the warm store: at least their recordings' bytes
    warm = find(overview, "#objects tr[data-tier='warm']")
    warm_runs = all_runs(console_depot, tier="warm")
    assert int(warm.get_attribute("data-bytes") or 0) >= sum(r["bytes"] for r in warm_runs) > 0
    assert int(warm.get_attribute("data-objects") or 0) >= 3 * len(warm_runs)
    disk = find(overview, "#hot-disk")
    assert int(disk.get_attribute("data-free") or 0) > 0 and int(disk.get_attribute("data-used") or 0) > 0
    assert "free" in text_of(overview, "#storage")


@pytest.mark.browser
@pytest.mark.slow
def test_hot_runs_and_retention_events(overview: webdriver.Chrome, console_depot: ConsoleDepot):
    hot = console_depot.runs["hot"]
    row = find(overview, f"#live tr[data-run='{hot}']")
    assert row.find_element(By.CSS_SELECTOR, "a").get_attribute("href") == f"{console_depot.url}/console/runs/{hot}"
    assert "this node" in row.text
    assert not overview.find_elements(By.CSS_SELECTOR, f"#live tr[data-run='{console_depot.runs['sealed']}']")
    events = text_of(overview, "#events")
    assert "promote" in events  # the fixture's sealed runs were promoted
    promoted = {a.text for a in overview.find_elements(By.CSS_SELECTOR, "#events tr[data-action='promote'] a")}
    rows = overview.find_elements(By.CSS_SELECTOR, "#events tbody tr")
    assert console_depot.runs["sealed-b"] in promoted or len(rows) == 10  # the latest ten: newer events may push it out
    screenshot(overview, "overview")


def test_failed_jobs_are_highlighted(fresh_catalog_url: str, tmp_path: Path):
    """The page as the template renders it from `fleet.overview` (no browser): a failed job run is
    flagged in the jobs table and named in an alert above it."""
    engine = create_engine(fresh_catalog_url)
    try:
        catalog = sessionmaker(engine)
        now = dt.datetime(2026, 11, 20, 12, tzinfo=dt.UTC)
        with session_scope(catalog, write=True) as session:
            queries.save_run(session, _record("r-1", now), now)
            ok = queries.start_job(session, "promote", "node-1", now)
            queries.finish_job(session, ok, now + dt.timedelta(seconds=2), "ok", "1 done, 0 failed")
            bad = queries.start_job(session, "retention", "node-1", now + dt.timedelta(minutes=1))
            queries.finish_job(session, bad, now + dt.timedelta(minutes=1), "failed", "OSError: the cold store refused")
        answer = fleet.overview(node_of(tmp_path, catalog), None, now=now)
    finally:
        engine.dispose()
    page = templates.get_template("overview.html").render(
        path=f"{PREFIX}/",
        principal=local_principal(),
        can={},
        csrf="x",
        auth_on=False,
        version=__version__,
        prefix=PREFIX,
        fleet=answer,
    )
    assert re.search(rf'<tr data-job="{bad}"[^>]*class="failed"', page)
    assert re.search(rf'<tr data-job="{ok}"[^>]*>', page) and page.count('class="failed"') == 1
    assert 'id="failures"' in page and "OSError: the cold store refused" in page
    assert "This node ingests nothing" in page and 'href="/console/runs/r-1"' in page


def _record(run_id: str, now: dt.datetime) -> RunRecord:
    return run_record(run_id, now, robot_id="robot-a", tier="warm")
