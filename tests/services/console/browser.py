"""Headless Chromium (Debian's `chromium` and `chromium-driver`) driven by Selenium, as a person
would use the console: pages loaded, forms filled, links followed, screenshots kept.

Real time, never virtual time: the Rerun web viewer needs it to start. Waits poll a condition until
it holds or the time runs out. Screenshots go to `FLEET_TEST_ARTIFACTS` (default
`build/test-artifacts/console/`), kept after the run as the tests' artifacts.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import pytest
from selenium import webdriver
from selenium.webdriver.chrome.options import Options
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webelement import WebElement

from tests import waiting

T = TypeVar("T")
ROOT = Path(__file__).resolve().parents[3]
ARTIFACTS = Path(os.environ.get("FLEET_TEST_ARTIFACTS", ROOT / "build" / "test-artifacts")) / "console"


def chromium_paths() -> tuple[str, str]:
    """Debian's Chromium and its driver; the test fails, naming the fix, if they are missing."""
    browser = shutil.which("chromium") or "/usr/bin/chromium"
    driver = shutil.which("chromedriver") or "/usr/bin/chromedriver"
    if not (Path(browser).exists() and Path(driver).exists()):
        pytest.fail("the browser tests need Chromium: apt-get install chromium chromium-driver (.ci/run does)")
    return browser, driver


def start_chrome(downloads: Path) -> webdriver.Chrome:
    """Headless Chromium with WebGL on SwiftShader (WebGPU finds no adapter headless: the Rerun web
    viewer falls back to WebGL2), downloads saved to `downloads`."""
    browser, driver = chromium_paths()
    options = Options()
    options.binary_location = browser
    for flag in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--window-size=1400,1000",
        "--use-gl=angle",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--no-first-run",
        "--disable-extensions",
        "--disable-background-networking",
    ):
        options.add_argument(flag)
    options.add_experimental_option(
        "prefs", {"download.default_directory": str(downloads), "download.prompt_for_download": False}
    )
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    chrome = webdriver.Chrome(options=options, service=Service(executable_path=driver))
    chrome.set_page_load_timeout(120)
    return chrome


def wait_for(condition: Callable[[], T | None], timeout: float, what: str) -> T:
    """Poll `condition` until it returns something truthy (returned), or fail naming `what`; while
    the page is still changing (a stale element, a node not there yet) the exception it raises
    counts as "not yet"."""
    return waiting.wait_for(condition, timeout, what, tolerate=(Exception,))


def text_of(chrome: webdriver.Chrome, css: str = "main") -> str:
    return str(chrome.find_element(By.CSS_SELECTOR, css).text)


def find(chrome: webdriver.Chrome, css: str) -> WebElement:
    return chrome.find_element(By.CSS_SELECTOR, css)


def log_in(chrome: webdriver.Chrome, base_url: str, token: str, then: str = "/console/") -> None:
    """Open the login page, paste the token, submit, and wait to land on `then`."""
    chrome.get(f"{base_url}/console/login?next={then}")
    find(chrome, "input[name=token]").send_keys(token)
    find(chrome, "form[action='/console/login'] button[type=submit]").click()
    wait_for(lambda: chrome.current_url.split("?")[0].endswith(then), 30, f"the console to land on {then}")


def forget_session(chrome: webdriver.Chrome, base_url: str) -> None:
    """No cookie of the console left: they are deleted from a page under /console (their path),
    the only place the browser sees them; a static file, which never redirects."""
    chrome.get(f"{base_url}/console/static/console.css")
    chrome.delete_all_cookies()


def log_out(chrome: webdriver.Chrome) -> None:
    find(chrome, "form[action='/console/logout'] button").click()
    wait_for(lambda: "/console/login" in chrome.current_url, 30, "the login page after logging out")


def screenshot(chrome: webdriver.Chrome, name: str) -> Path:
    """A screenshot of the whole window, kept as an artifact: ARTIFACTS/NAME.png."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    path = ARTIFACTS / f"{name}.png"
    chrome.save_screenshot(str(path))
    return path
