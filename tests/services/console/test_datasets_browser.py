"""Dataset snapshots in a real browser over a real depot: from the header's menu to a snapshot's
version, its episode window written as times, and "open in viewer" opening the web viewer at it."""

from __future__ import annotations

import uuid
from urllib.parse import parse_qs, urlsplit

import pytest
from selenium import webdriver
from selenium.webdriver.common.by import By

from core.timefmt import timeline_value
from tests.services.console.browser import find, log_in, screenshot, wait_for
from tests.services.console.conftest import ConsoleDepot

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_an_episode_opens_in_the_viewer_at_its_window(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> None:
    depot = console_depot
    run_id = depot.new_run("robot-a")
    span = next(t for t in depot.api("GET", f"/v1/runs/{run_id}").json()["timelines"] if t["name"] == "log_time")
    middle = (span["min"] + span["max"]) // 2
    kind = f"grasp-{uuid.uuid4().hex[:6]}"
    event = {"timeline": "log_time", "start": middle, "end": middle, "kind": kind, "label": "took it"}
    made = depot.api("POST", f"/v1/runs/{run_id}/events", depot.tokens["write"], json=event)
    assert made.status_code in (200, 201), made.text
    name = f"console-{kind}"
    body = {"name": name, "event_window": {"event": [kind], "before_s": 0.5, "after_s": 0.5}, "fps": 10}
    created = depot.api("POST", "/v1/datasets", depot.tokens["write"], json=body)
    assert created.status_code == 201, created.text
    (episode,) = depot.api("GET", f"/v1/datasets/{name}/1").json()["episodes_page"]

    log_in(chrome, depot.url, depot.tokens["read"], then="/console/runs")
    find(chrome, "header nav a[href='/console/datasets']").click()
    row = wait_for(lambda: find(chrome, f"#datasets tr[data-dataset='{name}']"), 30, "the snapshot in the list")
    assert row.find_element(By.CSS_SELECTOR, "a.ref").text == f"{name}@1"
    row.find_element(By.CSS_SELECTOR, "a.ref").click()
    wait_for(lambda: find(chrome, "#episodes tbody tr[data-episode='0']"), 30, "the version's episodes")
    windows = [td.text for td in chrome.find_elements(By.CSS_SELECTOR, "#episodes tbody tr td.window")]
    assert windows == [timeline_value("timestamp", episode["start"]), timeline_value("timestamp", episode["end"])]
    assert find(chrome, "#episodes a.episode-run").text == run_id
    screenshot(chrome, "dataset-version")

    find(chrome, "#episodes a.episode-view").click()
    wait_for(lambda: "/viewer" in chrome.current_url, 30, "the viewer's page")
    opened = urlsplit(chrome.current_url)
    assert opened.path == f"/console/runs/{run_id}/viewer"
    assert {k: v[0] for k, v in parse_qs(opened.query).items()} == {
        "timeline": "log_time",
        "start": str(episode["start"]),
        "end": str(episode["end"]),
    }
    window = find(chrome, "#viewer-window")
    assert window.get_attribute("data-start") == str(episode["start"])
