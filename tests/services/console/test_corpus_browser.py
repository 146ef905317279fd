"""The corpus in a real browser over a real depot: an event marked on a run's coverage opens the
web viewer at the event's window when clicked."""

from __future__ import annotations

import re
from urllib.parse import parse_qs, urlsplit

import pytest
from selenium import webdriver

from tests.services.console.browser import find, log_in, screenshot, text_of, wait_for
from tests.services.console.conftest import ConsoleDepot

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def test_clicking_an_event_mark_opens_the_viewer_at_its_window(
    chrome: webdriver.Chrome, console_depot: ConsoleDepot
) -> None:
    depot = console_depot
    run_id = depot.new_run("robot-a")
    log_in(chrome, depot.url, depot.tokens["read"], then=f"/console/runs/{run_id}")
    heading = wait_for(lambda: text_of(chrome, "#coverage h2"), 30, "the coverage")
    found = re.search(r"on (\S+)$", heading)
    assert found, heading
    timeline = found.group(1)
    span = next(t for t in depot.api("GET", f"/v1/runs/{run_id}").json()["timelines"] if t["name"] == timeline)
    start = span["min"] + (span["max"] - span["min"]) // 3
    end = span["min"] + 2 * (span["max"] - span["min"]) // 3
    body = {"timeline": timeline, "start": start, "end": end, "label": "looked odd"}
    made = depot.api("POST", f"/v1/runs/{run_id}/events", depot.tokens["write"], json=body)
    assert made.status_code in (200, 201), made.text
    event = made.json()

    chrome.refresh()
    mark = wait_for(lambda: find(chrome, f"svg.coverage a.event-mark[data-event='{event['id']}'] rect"), 30, "the mark")
    chrome.execute_script("arguments[0].scrollIntoView({block: 'center'})", find(chrome, "#coverage"))
    screenshot(chrome, "run-event-marks")
    mark.click()
    wait_for(lambda: "/viewer" in chrome.current_url, 30, "the viewer's page")
    opened = urlsplit(chrome.current_url)
    assert opened.path == f"/console/runs/{run_id}/viewer"
    pad = 0 if span["type"] == "sequence" else 5_000_000_000
    assert {k: v[0] for k, v in parse_qs(opened.query).items()} == {
        "timeline": timeline,
        "start": str(start - pad),
        "end": str(end + pad),
    }
    window = find(chrome, "#viewer-window")
    assert window.get_attribute("data-start") == str(start - pad) and window.get_attribute("data-end") == str(end + pad)
