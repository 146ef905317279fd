"""Logging in to the console in a real browser: who gets in, who is refused and why, and how a
session ends (logging out, the token revoked)."""

from __future__ import annotations

import pytest
from selenium import webdriver

from services.console.web import SESSION_COOKIE
from tests.services.console.browser import find, log_in, log_out, text_of, wait_for
from tests.services.console.conftest import ConsoleDepot

pytestmark = [pytest.mark.browser, pytest.mark.slow]


def submit_token(chrome: webdriver.Chrome, url: str, token: str) -> None:
    """Paste a token at the login page and submit it, wherever that leads."""
    chrome.get(f"{url}/console/login")
    find(chrome, "input[name=token]").send_keys(token)
    find(chrome, "form[action='/console/login'] button[type=submit]").click()


def refusal(chrome: webdriver.Chrome) -> str:
    """The login page's problem, once it shows one."""
    return wait_for(lambda: text_of(chrome, ".problem"), 30, "the login page's problem")


def has_session(chrome: webdriver.Chrome) -> bool:
    return any(cookie["name"] == SESSION_COOKIE for cookie in chrome.get_cookies())


def test_read_token_lands_on_the_overview(chrome: webdriver.Chrome, console_depot: ConsoleDepot):
    log_in(chrome, console_depot.url, console_depot.tokens["read"])
    assert wait_for(lambda: "Fleet overview" in text_of(chrome, "h1"), 30, "the overview's title")
    badges = text_of(chrome, "header .who")
    assert "read" in badges and "admin" not in badges
    assert has_session(chrome)


def test_ingest_token_is_refused_with_the_reason(chrome: webdriver.Chrome, console_depot: ConsoleDepot):
    submit_token(chrome, console_depot.url, console_depot.tokens["ingest"])
    problem = refusal(chrome)
    assert "reads nothing" in problem and "read, write or admin token" in problem
    assert "/console/login" in chrome.current_url and not has_session(chrome)


def test_bad_token_is_refused(chrome: webdriver.Chrome, console_depot: ConsoleDepot):
    submit_token(chrome, console_depot.url, "not-a-token-of-this-depot")
    assert refusal(chrome)
    assert "/console/login" in chrome.current_url and not has_session(chrome)
    chrome.get(f"{console_depot.url}/console/")  # still no way in
    wait_for(lambda: "/console/login" in chrome.current_url, 30, "the login page")


def test_logout_ends_the_session(chrome: webdriver.Chrome, console_depot: ConsoleDepot):
    log_in(chrome, console_depot.url, console_depot.tokens["read"], then="/console/runs")
    log_out(chrome)
    assert not has_session(chrome)
    chrome.get(f"{console_depot.url}/console/runs?tier=warm")
    wait_for(lambda: "/console/login" in chrome.current_url, 30, "the login page after logging out")
    assert "next=/console/runs%3Ftier%3Dwarm" in chrome.current_url
    assert find(chrome, "input[name=token]").is_displayed()


def test_a_revoked_tokens_session_stops_working(chrome: webdriver.Chrome, console_depot: ConsoleDepot):
    token = console_depot.token("read")
    token_id = console_depot.api("GET", "/v1/whoami", token=token).json()["token"]
    log_in(chrome, console_depot.url, token)
    chrome.get(f"{console_depot.url}/console/runs")
    wait_for(lambda: "Runs" in text_of(chrome, "h1"), 30, "the runs page while the token stands")
    answer = console_depot.api("DELETE", f"/v1/tokens/{token_id}")
    assert answer.status_code == 200, answer.text
    chrome.get(f"{console_depot.url}/console/runs")
    wait_for(lambda: "/console/login" in chrome.current_url, 30, "the login page once the token is revoked")
    assert has_session(chrome)  # the cookie is still there: the depot no longer honours it
