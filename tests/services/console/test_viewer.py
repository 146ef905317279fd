"""The Rerun web viewer served by the depot (from the rerun-notebook package) opens a sealed run in
headless Chromium: the canvas renders something (screenshot checked), under the viewer page's own
Content-Security-Policy with nothing refused; its assets have the right types and long caching."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest
from selenium import webdriver

from services.console.viewer import VIEWER_CSP, viewer_assets
from tests.services.console.browser import find, forget_session, log_in, screenshot, text_of, wait_for
from tests.services.console.conftest import ConsoleDepot
from tests.viewer import assert_not_blank, image_stats

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def logged_in(chrome: webdriver.Chrome, depot: ConsoleDepot, then: str) -> None:
    forget_session(chrome, depot.url)
    log_in(chrome, depot.url, depot.tokens["read"], then=then)


def rendered(chrome: webdriver.Chrome, tmp: Path) -> Path | None:
    """A picture of the viewer once it says it is ready and its canvas shows the run (many colours,
    much off the background: panels, the plot, the points; the loading screen has few), else None."""
    viewer = find(chrome, "#viewer")
    if viewer.get_attribute("data-state") not in ("ready", "loaded"):
        return None
    shot = tmp / "viewer-element.png"
    viewer.screenshot(str(shot))
    stats = image_stats(shot)
    return shot if stats.colours >= 500 and stats.foreground >= 0.05 else None


def test_viewer_renders_a_sealed_run(chrome: webdriver.Chrome, console_depot: ConsoleDepot, tmp_path: Path) -> None:
    depot, run_id = console_depot, console_depot.runs["sealed"]
    page = f"/console/runs/{run_id}/viewer"
    logged_in(chrome, depot, page)
    viewer = find(chrome, "#viewer")
    url = viewer.get_attribute("data-url") or ""
    assert url.startswith(f"/v1/runs/{run_id}/recording.rrd?")  # fetched from the page's own origin
    assert f'rerun "{depot.url}/v1/runs/{run_id}/recording.rrd?' in text_of(chrome, ".viewer-bar")

    shot = wait_for(lambda: rendered(chrome, tmp_path), 120, "the web viewer to render the run")
    assert_not_blank(shot, min_colours=500, min_foreground=0.05)
    assert_not_blank(screenshot(chrome, "viewer"))
    # the page's status follows the viewer: once the run is on screen it no longer says "loading"
    wait_for(lambda: find(chrome, "#viewer").get_attribute("data-state") == "loaded", 60, "the status to say loaded")
    assert "loading" not in text_of(chrome, "#viewer-status").lower()
    # Nothing the viewer needs is refused by the page's policy. The one refusal expected is its
    # check for a newer release on api.github.com, kept from calling out by connect-src 'self'.
    refused = [
        entry["message"]
        for entry in chrome.get_log("browser")
        if ("Content Security Policy" in entry["message"] or "Refused to" in entry["message"])
        and "https://api.github.com/" not in entry["message"]
    ]
    assert refused == [], refused


def test_viewer_page_and_assets_headers(chrome: webdriver.Chrome, console_depot: ConsoleDepot) -> None:
    depot, run_id = console_depot, console_depot.runs["sealed"]
    logged_in(chrome, depot, f"/console/runs/{run_id}")
    assets = viewer_assets()
    assert assets is not None
    cookies = {c["name"]: c["value"] for c in chrome.get_cookies()}
    with httpx.Client(base_url=depot.url, cookies=cookies, timeout=60) as client:
        page = client.get(f"/console/runs/{run_id}/viewer")
        assert page.status_code == 200
        assert page.headers["content-security-policy"] == VIEWER_CSP
        assert "'wasm-unsafe-eval'" in VIEWER_CSP and "'unsafe-eval'" not in VIEWER_CSP
        run_page = client.get(f"/console/runs/{run_id}")
        assert "wasm-unsafe-eval" not in run_page.headers["content-security-policy"]  # that page only

        base = f"/console/viewer-assets/{assets.version}"
        with client.stream("GET", f"{base}/re_viewer_bg.wasm") as wasm:
            assert wasm.status_code == 200
            assert wasm.headers["content-type"] == "application/wasm"
            assert "immutable" in wasm.headers["cache-control"]
            assert next(wasm.iter_bytes()).startswith(b"\0asm")
        widget = client.get(f"{base}/widget.js")
        assert widget.headers["content-type"].startswith("text/javascript")
        assert client.get("/console/viewer-assets/0.0.0/widget.js").status_code == 404  # another version
        assert client.get(f"{base}/__init__.py").status_code == 404  # only the viewer's files
    anonymous = httpx.get(f"{depot.url}{base}/widget.js", follow_redirects=False, timeout=30)
    assert anonymous.status_code == 303  # to the login page
