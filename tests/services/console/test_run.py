"""A run's page in a real browser over a real depot: what it shows (facts, entity tree with the
API's counts, scalar plot, text logs, for a sealed and a hot run), its actions by scope (refused
without the scope even when posted by hand), and the filtered download by signed link."""

from __future__ import annotations

import datetime as dt
import subprocess
from pathlib import Path
from typing import Any

import httpx
import pytest
from selenium import webdriver
from selenium.webdriver.common.by import By

from services.console.run import entity_tree, patterns
from services.console.viewer import viewer_assets
from services.policies import Policies, Policy
from services.rrd import ArrowMessage, StoreKind, iter_events
from services.rrd.chunk import chunk_meta
from services.runs.run_views import next_step
from tests.services.console.browser import find, forget_session, log_in, screenshot, text_of, wait_for
from tests.services.console.conftest import ConsoleDepot

FRAMES = 60  # frames each run of the console's depot logs (conftest.SCRIPT)


def page_of(run_id: str) -> str:
    return f"/console/runs/{run_id}"


def open_run(chrome: webdriver.Chrome, depot: ConsoleDepot, scope: str, run_id: str) -> None:
    forget_session(chrome, depot.url)
    log_in(chrome, depot.url, depot.tokens[scope], then=page_of(run_id))
    try:
        wait_for(lambda: find(chrome, "#entities"), 30, "the run's page")
    except AssertionError as exc:  # say what the browser shows instead
        shown = text_of(chrome, "body")[:2000]
        raise AssertionError(f"{exc}; the browser shows {chrome.current_url}: {shown}") from None


def browser_client(chrome: webdriver.Chrome, depot: ConsoleDepot) -> httpx.Client:
    """An HTTP client holding the browser's cookies (its session and CSRF value): the requests a
    page's forms make, sent by hand."""
    cookies = {c["name"]: c["value"] for c in chrome.get_cookies()}
    return httpx.Client(base_url=depot.url, cookies=cookies, timeout=60)


def api_run(depot: ConsoleDepot, run_id: str) -> dict[str, Any]:
    answer = depot.api("GET", f"/v1/runs/{run_id}")
    assert answer.status_code == 200, answer.text
    return dict(answer.json())


# --- the page -------------------------------------------------------------------------------------


@pytest.mark.browser
@pytest.mark.slow
def test_sealed_run_page_shows_the_run(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> None:
    depot, run_id = console_depot, console_depot.runs["sealed"]
    answer = api_run(depot, run_id)
    open_run(chrome, depot, "read", run_id)

    assert text_of(chrome, "#robot") == "robot-a"
    assert find(chrome, ".badge[data-tier]").get_attribute("data-tier") == answer["tier"] == "warm"
    for entity in answer["entities"]:  # the tree with the API's counts
        row = find(chrome, f"tr[data-entity='{entity['path']}']")
        assert row.find_element(By.CSS_SELECTOR, "td.chunks").text == f"{entity['chunks']:,}"
        assert row.find_element(By.CSS_SELECTOR, "td.rows").text == f"{entity['rows']:,}"
    paths = {e["path"] for e in answer["entities"]}
    assert {"/battery/voltage", "/world/points", "/logs"} <= paths
    assert find(chrome, "tr[data-entity='/battery']").get_attribute("class") == "branch"  # a parent only

    plot = find(chrome, "figure.plot[data-entity='/battery/voltage']")
    line = plot.find_element(By.CSS_SELECTOR, "svg polyline")
    assert int(line.get_attribute("data-points") or 0) == FRAMES
    assert len((line.get_attribute("points") or "").split()) == FRAMES
    assert "analytics tables" in text_of(chrome, "#plots")

    logs = text_of(chrome, "#logs")
    assert "battery low" in logs and "WARN" in logs and "frame 0: all good" in logs
    rows = chrome.find_elements(By.CSS_SELECTOR, "#logs tbody tr")
    assert "battery low" in rows[-1].text  # newest last

    assert find(chrome, "#coverage svg.coverage rect[data-label='/battery/voltage']")
    assert "site" in text_of(chrome, "#properties") and "lab-2" in text_of(chrome, "#properties")
    assert "archive" in text_of(chrome, "#next-step")  # the default policy: warm, then cold
    command = text_of(chrome, "#rerun-command")
    assert command.startswith(f'rerun "{depot.url}/v1/runs/{run_id}/recording.rrd?') and "sig" in command.lower()
    screenshot(chrome, "run-page")


@pytest.mark.browser
@pytest.mark.slow
def test_hot_run_page_plots_from_the_run_itself(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> None:
    depot, run_id = console_depot, console_depot.runs["hot"]
    open_run(chrome, depot, "read", run_id)
    assert find(chrome, ".badge[data-tier]").get_attribute("data-tier") == "hot"
    assert "hot run" in text_of(chrome, "#plots")
    line = find(chrome, "figure.plot[data-entity='/battery/voltage'] svg polyline")
    assert int(line.get_attribute("data-points") or 0) == FRAMES
    assert "battery low" in text_of(chrome, "#logs")
    assert "promote" in text_of(chrome, "#next-step")


@pytest.mark.browser
@pytest.mark.slow
def test_unknown_run_is_a_404_page(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> None:
    forget_session(chrome, console_depot.url)
    log_in(chrome, console_depot.url, console_depot.tokens["read"])
    chrome.get(f"{console_depot.url}{page_of('no-such-run')}")
    assert "no-such-run" in text_of(chrome, "main") and "404" in text_of(chrome, "main")


# --- actions by scope -----------------------------------------------------------------------------


@pytest.mark.browser
@pytest.mark.slow
def test_read_token_sees_no_actions_and_a_crafted_post_is_refused(
    chrome: webdriver.Chrome, console_depot: ConsoleDepot
) -> None:
    depot, run_id = console_depot, console_depot.runs["sealed-b"]
    open_run(chrome, depot, "read", run_id)
    assert chrome.find_elements(By.CSS_SELECTOR, "#actions") == []
    assert chrome.find_elements(By.CSS_SELECTOR, "form[action$='/pin'], form[action$='/delete']") == []
    csrf = find(chrome, "form[action='/console/logout'] input[name=csrf]").get_attribute("value")
    with browser_client(chrome, depot) as client:
        for action in ("pin", "delete", "promote", "pull"):
            refused = client.post(f"{page_of(run_id)}/{action}", data={"csrf": csrf, "confirm": run_id})
            assert refused.status_code == 403, (action, refused.text)
            assert "scope" in refused.text
        page = client.get(page_of(run_id))  # the same session and CSRF value do read
        assert page.status_code == 200
    assert api_run(depot, run_id)["pinned"] is False
    assert api_run(depot, run_id)["tier"] == "warm"


@pytest.mark.browser
@pytest.mark.slow
def test_write_token_pins_and_unpins(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> None:
    depot, run_id = console_depot, console_depot.runs["sealed-b"]
    open_run(chrome, depot, "write", run_id)
    assert chrome.find_elements(By.CSS_SELECTOR, "#delete-form") == []  # deleting needs admin
    find(chrome, "#pin").click()
    wait_for(lambda: "Pinned" in text_of(chrome, "#notice"), 30, "the pin's notice")
    assert find(chrome, "#pinned")
    answer = api_run(depot, run_id)
    assert answer["pinned"] is True and answer["pinned_by"]
    find(chrome, "#unpin").click()
    wait_for(lambda: "Unpinned" in text_of(chrome, "#notice"), 30, "the unpin's notice")
    assert api_run(depot, run_id)["pinned"] is False
    assert {"pin", "unpin"} <= {e["action"] for e in api_run(depot, run_id)["events"]}


@pytest.mark.browser
@pytest.mark.slow
def test_write_token_pull_is_queued(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> None:
    depot, run_id = console_depot, console_depot.runs["sealed-b"]
    open_run(chrome, depot, "write", run_id)
    find(chrome, "#pull-form input[name=include]").send_keys("/world/**")
    find(chrome, "#pull").click()
    wait_for(lambda: "ull" in text_of(chrome, "#notice"), 30, "the pull's notice")
    pulls = depot.api("GET", f"/v1/runs/{run_id}/pulls").json()["pulls"]
    assert any(p["include"] == ["/world/**"] for p in pulls), pulls


@pytest.mark.browser
@pytest.mark.slow
def test_admin_deletes_a_run_after_confirming(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> None:
    depot = console_depot
    run_id = depot.new_run("robot-a")
    open_run(chrome, depot, "admin", run_id)
    form = find(chrome, "#delete-form")
    assert "cannot be undone" in (form.get_attribute("data-confirm") or "")
    find(chrome, "#delete-form input[name=confirm]").send_keys("not-the-id")
    find(chrome, "#delete").click()
    wait_for(lambda: chrome.switch_to.alert, 10, "the confirmation dialog").accept()
    wait_for(lambda: "type the run's id" in text_of(chrome, "#problem"), 30, "the refusal of a wrong confirmation")
    assert api_run(depot, run_id)["tier"] == "warm"

    find(chrome, "#delete-form input[name=confirm]").send_keys(run_id)
    find(chrome, "#delete").click()
    wait_for(lambda: chrome.switch_to.alert, 10, "the confirmation dialog").accept()
    try:
        wait_for(lambda: "Deleted" in text_of(chrome, "#notice"), 60, "the deletion's notice")
    except AssertionError as exc:
        shown = text_of(chrome, "body")[:1500]
        raise AssertionError(f"{exc}; the browser shows {chrome.current_url}: {shown}") from None
    assert api_run(depot, run_id)["tier"] == "deleted"
    assert depot.api("GET", f"/v1/runs/{run_id}/recording.rrd").status_code == 410
    assert chrome.find_elements(By.CSS_SELECTOR, "#delete-form, #pin") == []


# --- download -------------------------------------------------------------------------------------


def recording_paths(path: Path) -> set[str]:
    return {
        str(chunk_meta(e).entity_path)
        for e in iter_events(path)
        if isinstance(e, ArrowMessage) and e.store_id.kind == StoreKind.RECORDING
    }


@pytest.mark.browser
@pytest.mark.slow
def test_filtered_download_by_signed_link(
    chrome: webdriver.Chrome, console_depot: ConsoleDepot, tmp_path: Path, rerun_bin: str
) -> None:
    depot, run_id = console_depot, console_depot.runs["sealed"]
    open_run(chrome, depot, "read", run_id)
    form = find(chrome, "#download-form")
    assert form.get_attribute("method") == "get"
    with browser_client(chrome, depot) as client:
        asked = {"include": "/battery/**", "timeline": "frame", "start": "10", "end": "19"}
        answer = client.get(f"{page_of(run_id)}/download", params=asked)
        assert answer.status_code == 303, answer.text
        link = answer.headers["location"]
        assert link.startswith(f"/v1/runs/{run_id}/recording.rrd?")  # on the origin the browser used
        got = httpx.get(f"{depot.url}{link}", timeout=60)  # no header: the link's signature is the credential
        assert got.status_code == 200, got.text
        assert "attachment" in got.headers["content-disposition"]
        bad = client.get(f"{page_of(run_id)}/download", params={"timeline": "nope", "start": "1"})
        assert bad.status_code == 422 and "nope" in bad.text  # shown on the page, not downloaded
    out = tmp_path / "part.rrd"
    out.write_bytes(got.content)
    paths = recording_paths(out) - {"/__properties"}
    assert paths and all(p.startswith("/battery") or p.startswith("/__properties") for p in paths), paths
    assert subprocess.run([rerun_bin, "rrd", "verify", str(out)], capture_output=True).returncode == 0


# --- fast: pieces of the page ---------------------------------------------------------------------


def test_entity_tree_adds_parents_in_order() -> None:
    tree = entity_tree([{"path": "/world/points"}, {"path": "/battery/voltage"}, {"path": "/world"}])
    assert [(n.path, n.depth, n.entity is not None) for n in tree] == [
        ("/battery", 0, False),
        ("/battery/voltage", 1, True),
        ("/world", 0, True),
        ("/world/points", 1, True),
    ]


def test_patterns_split_on_spaces_and_commas() -> None:
    assert patterns(" /a/** , /b\n/c ") == ["/a/**", "/b", "/c"]
    assert patterns(None) == []


def test_next_step_by_policy() -> None:
    policies = Policies(Policy("default", 30, 60))
    answer = {
        "tier": "warm",
        "robot_id": "r",
        "application_id": "a",
        "ended_at": "2026-01-01T00:00:00+00:00",
        "pinned": False,
        "lifecycle": {},
    }
    now = dt.datetime(2026, 1, 2, tzinfo=dt.UTC)
    step = next_step(answer, policies, now)
    assert step.action == "archive" and step.at is not None and step.at.startswith("2026-01-31")
    assert next_step({**answer, "tier": "cold"}, policies, now).action == "delete"
    assert next_step({**answer, "tier": "cold", "pinned": True}, policies, now).action == "nothing"


def test_viewer_assets_missing_package_is_none() -> None:
    assert viewer_assets("no_such_viewer_package") is None
    found = viewer_assets()
    assert found is not None and found.path("re_viewer_bg.wasm").is_file()
