"""The console's login, session cookie and CSRF checks, on the app as `fleet serve` wires it (auth on)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import TypeVar

import httpx
import pytest

from services.auth.sessions import close_session, csrf_value, session_principal
from services.auth.tokens import Auth
from services.cli.serve import console_address
from services.console.app import ROUTERS, install
from services.console.login import safe_next
from services.console.web import CSP, CSRF_COOKIE, SESSION_COOKIE
from services.settings import load_settings
from tests.services.auth.conftest import Depot, open_depot

CSRF = re.compile(r'name="csrf" value="([^"]+)"')
ALERT = re.compile(r'role="alert">([^<]+)<')
Client = TypeVar("Client", bound=httpx.Client)  # a TestClient, or an httpx client of a real server


@pytest.fixture
def console(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    with open_depot(tmp_path, fresh_catalog_url) as depot:
        install(depot.app)
        yield depot


def login_form(client: httpx.Client) -> str:
    page = client.get("/console/login")
    assert page.status_code == 200
    found = CSRF.search(page.text)
    assert found
    return found.group(1)


def log_in(client: Client, token: str, nxt: str = "/console/runs") -> Client:
    csrf = login_form(client)
    answer = client.post("/console/login", data={"token": token, "csrf": csrf, "next": nxt}, follow_redirects=False)
    assert answer.status_code == 303, answer.text
    return client


def test_the_login_page_carries_the_security_headers_and_a_csrf_cookie(console: Depot) -> None:
    page = console.client.get("/console/login")
    assert page.headers["content-security-policy"] == CSP
    assert page.headers["x-content-type-options"] == "nosniff"
    cookie = page.headers["set-cookie"]
    assert cookie.startswith(f"{CSRF_COOKIE}=") and "HttpOnly" in cookie and "SameSite=strict" in cookie
    assert "Path=/console" in cookie


def test_a_console_page_without_a_session_goes_to_the_login_page_and_back(console: Depot) -> None:
    answer = console.client.get("/console/runs?robot=robot-a", follow_redirects=False)
    assert answer.status_code == 303
    assert answer.headers["location"] == "/console/login?next=/console/runs%3Frobot%3Drobot-a"


def test_a_token_becomes_a_session_cookie_that_is_not_the_token(console: Depot) -> None:
    token = console.token("read")
    csrf = login_form(console.client)
    answer = console.client.post(
        "/console/login", data={"token": token, "csrf": csrf, "next": "/console/runs"}, follow_redirects=False
    )
    assert answer.status_code == 303 and answer.headers["location"] == "/console/runs"
    cookie = answer.headers["set-cookie"]
    assert cookie.startswith(f"{SESSION_COOKIE}=") and "HttpOnly" in cookie and "SameSite=lax" in cookie
    session = console.client.cookies[SESSION_COOKIE]
    assert session != token and token not in cookie
    # The session is no API token: a bearer of it is refused.
    assert console.client.get("/v1/runs", headers={"Authorization": f"Bearer {session}"}).status_code == 401


@pytest.mark.parametrize(
    ("make", "status", "said"),
    [
        (lambda d: d.token("ingest", robot="robot-1"), 403, "reads nothing"),
        (lambda d: "not-a-token", 401, "not a valid token"),
        (lambda d: d.revoked_token("read"), 401, "revoked"),
        (lambda d: d.expired_token("read"), 401, "expired"),
    ],
)
def test_tokens_that_may_not_log_in_are_refused_with_the_reason(
    console: Depot, make: object, status: int, said: str
) -> None:
    token = make(console)  # type: ignore[operator]
    csrf = login_form(console.client)
    answer = console.client.post("/console/login", data={"token": token, "csrf": csrf}, follow_redirects=False)
    assert answer.status_code == status
    alert = ALERT.search(answer.text)
    assert alert and said in alert.group(1)
    assert SESSION_COOKIE not in console.client.cookies


def test_a_post_without_the_csrf_value_or_from_another_site_is_refused(console: Depot) -> None:
    token = console.token("read")
    csrf = login_form(console.client)
    for data, headers in (
        ({"token": token}, {}),
        ({"token": token, "csrf": "forged"}, {}),
        ({"token": token, "csrf": csrf}, {"origin": "https://evil.example"}),
    ):
        answer = console.client.post("/console/login", data=data, headers=headers, follow_redirects=False)
        assert answer.status_code == 403, (data, headers)
        assert SESSION_COOKIE not in console.client.cookies


def test_revoking_the_token_ends_its_sessions(console: Depot) -> None:
    issued = console.issue("read", name="alice")
    client = log_in(console.client, issued.token)
    assert client.get("/console/login", follow_redirects=False).status_code == 303  # logged in: sent on
    console.auth.revoke(issued.record.id, "test")
    console.auth._known.clear()  # the token cache (auth_cache_s) would hold the answer a few seconds
    answer = client.get("/console/login", follow_redirects=False)
    assert answer.status_code == 200 and "Log in" in answer.text


def test_logging_out_needs_the_csrf_value_and_drops_the_session(console: Depot) -> None:
    client = log_in(console.client, console.token("read"))
    assert client.post("/console/logout", data={}, follow_redirects=False).status_code == 403
    page = client.get("/console/login?next=/console/", follow_redirects=False)
    assert page.status_code == 303  # still logged in
    # Once logged in, forms carry the session's own CSRF value: the login form's one no longer does.
    login_csrf = client.cookies[CSRF_COOKIE]
    assert client.post("/console/logout", data={"csrf": login_csrf}, follow_redirects=False).status_code == 403
    value = csrf_value(console.auth, client.cookies[SESSION_COOKIE], login_csrf)
    answer = client.post("/console/logout", data={"csrf": value}, follow_redirects=False)
    assert answer.status_code == 303 and answer.headers["location"] == "/console/login"
    assert SESSION_COOKIE not in client.cookies


def test_a_session_cookie_is_refused_after_logging_out(console: Depot) -> None:
    token = console.token("read")
    client = log_in(console.client, token)
    old = client.cookies[SESSION_COOKIE]  # a copy of the cookie: kept by another tab, a proxy, a thief
    assert client.get("/console/runs", follow_redirects=False).status_code == 200
    value = csrf_value(console.auth, old, client.cookies[CSRF_COOKIE])
    assert client.post("/console/logout", data={"csrf": value}, follow_redirects=False).status_code == 303
    client.cookies.clear()
    client.cookies.set(SESSION_COOKIE, old)  # the old cookie, sent again
    answer = client.get("/console/runs", follow_redirects=False)
    assert answer.status_code == 303 and answer.headers["location"].startswith("/console/login")
    # another node of the depot (the same catalog and key) refuses it too, at once
    other = Auth(enabled=True, keys=console.auth.keys, catalog=console.auth.catalog)
    assert session_principal(other, old) is None
    # a new login with the same token is a new session, unaffected
    client.cookies.clear()
    again = log_in(client, token)
    assert again.get("/console/runs", follow_redirects=False).status_code == 200


def test_logging_out_without_a_session_or_twice_is_harmless(console: Depot) -> None:
    client = log_in(console.client, console.token("read"))
    old = client.cookies[SESSION_COOKIE]
    close_session(console.auth, old)
    close_session(console.auth, old)  # ending it again changes nothing
    close_session(console.auth, None)
    close_session(console.auth, "not-a-session")
    assert session_principal(console.auth, old) is None


@pytest.mark.parametrize(
    ("asked", "goes"),
    [
        ("/console/runs?robot=a", "/console/runs?robot=a"),
        ("https://evil.example/console/", "/console/"),
        ("//evil.example/console/", "/console/"),
        ("/v1/runs", "/console/"),
        ("/console/\\evil", "/console/"),
        (None, "/console/"),
    ],
)
def test_after_logging_in_the_browser_goes_only_to_a_console_page(asked: str | None, goes: str) -> None:
    assert safe_next(asked) == goes


def test_the_console_address_printed_at_start() -> None:
    assert console_address(load_settings(http_addr="0.0.0.0:8080")) == "http://localhost:8080/console/"
    assert console_address(load_settings(http_addr="127.0.0.1:9000")) == "http://127.0.0.1:9000/console/"
    assert console_address(load_settings(http_addr="[::1]:8080")) == "http://[::1]:8080/console/"
    assert console_address(load_settings(public_url="https://depot.example/")) == "https://depot.example/console/"


OPEN = {("GET", "/console/login"), ("POST", "/console/login")}


def test_every_console_route_needs_a_session(console: Depot) -> None:
    """Without a session a console page sends the browser to log in and an action is refused: none
    answers with content (the routes listed in OPEN are the login's own)."""
    checked = 0
    for route in (r for router in ROUTERS for r in router.routes):
        path = getattr(route, "path", "")
        url = re.sub(r"\{[^}]+\}", "x", path)
        for method in sorted(getattr(route, "methods", None) or ()):
            if (method, path) in OPEN or method == "HEAD":
                continue
            answer = console.client.request(method, url, follow_redirects=False)
            refused = answer.status_code == 403 or (
                answer.status_code == 303 and answer.headers["location"].startswith("/console/login")
            )
            assert refused, f"{method} {path} answered {answer.status_code} without a session"
            checked += 1
    assert checked >= 15, checked
