"""The address written into signed links and redirects is the depot's, never one a client's `Host`
header names: FLEET_PUBLIC_URL, else the request's address when it is one of the depot's names
(FLEET_PUBLIC_HOSTS) on its port, else the bind address. A redirect Starlette makes on its own (a
trailing slash) stays a path on the origin the client asked."""

from __future__ import annotations

import re
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.console.app import install
from services.runs.links import public_base
from services.settings import load_settings
from tests.conftest import fresh_catalog
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.console.test_sessions import log_in
from tests.services.rrd.recordings import Recording

FORGED = {"Host": "evil.example"}
RUN = "rec-points"
HOSTS = ["localhost", "127.0.0.1", "depot.example.com", "::1"]


def base(host: str | None, *, scheme: str = "http", **settings: str) -> str:
    return public_base(load_settings(**settings), HOSTS, host, scheme)


def test_the_configured_public_url_wins():
    assert base("evil.example", public_url="https://depot.example.com/") == "https://depot.example.com"
    assert base("localhost:8080", public_url="https://depot.example.com") == "https://depot.example.com"


@pytest.mark.parametrize(
    ("host", "expected"),
    [
        ("localhost:8080", "http://localhost:8080"),
        ("DEPOT.example.com:8080", "http://depot.example.com:8080"),
        ("depot.example.com", "http://depot.example.com"),  # behind a proxy on the default port
        ("[::1]:8080", "http://[::1]:8080"),
        ("127.0.0.1:8080", "http://127.0.0.1:8080"),
    ],
)
def test_the_request_address_is_used_when_it_is_one_of_the_depots_names(host: str, expected: str):
    assert base(host, http_addr="0.0.0.0:8080") == expected


@pytest.mark.parametrize(
    "host",
    [
        "evil.example",
        "evil.example:8080",
        "localhost:6666",  # a name of the depot, but not its port
        "localhost@evil.example:8080",
        "localhost:8080/evil",
        "localhost:80x",
        "[::1",
        "",
        None,
    ],
)
def test_any_other_host_header_gives_the_bind_address(host: str | None):
    assert base(host, http_addr="10.0.0.5:8080") == "http://10.0.0.5:8080"
    assert base(host, http_addr="0.0.0.0:8080") == f"http://{socket.gethostname()}:8080"
    assert base(host, http_addr="[fd00::5]:9000") == "http://[fd00::5]:9000"


def test_the_bind_address_is_one_of_the_depots_names():
    assert base("10.0.0.5:8080", http_addr="10.0.0.5:8080", scheme="https") == "https://10.0.0.5:8080"


# --- on the app as fleet serve wires it (REST and console) --------------------------------------


@pytest.fixture
def depot(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Depot]:
    """A depot (embedded catalog: what is tested here is the same on both) with its console."""
    with fresh_catalog("duckdb", request, tmp_path) as url, open_depot(tmp_path, url) as opened:
        install(opened.app)
        yield opened


@pytest.mark.parametrize("path", ["/v1/runs/", "/v1/whoami/", "/console/runs/", "/console/login/", "/console/static"])
def test_a_redirect_never_names_the_host_a_client_sent(depot: Depot, path: str):
    answer = depot.client.get(path, headers=FORGED, follow_redirects=False)
    assert answer.status_code == 307
    location = answer.headers["location"]
    assert location.startswith("/") and not location.startswith("//") and "evil" not in location, location


@pytest.fixture
def uploaded(depot: Depot, scenes: dict[str, Recording]) -> Depot:
    answer = depot.client.post("/v1/uploads", content=scenes["points"].data, headers=bearer(depot.token("write")))
    assert answer.status_code == 200, answer.text
    return depot


BOUND = f"http://{socket.gethostname()}:8080"  # the test depot binds 0.0.0.0:8080 (the default)


@pytest.mark.sdk
def test_a_signed_link_never_names_the_host_a_client_sent(uploaded: Depot):
    asked = uploaded.client.post(f"/v1/runs/{RUN}/links", headers={**bearer(uploaded.token("read")), **FORGED})
    assert asked.status_code == 200, asked.text
    assert asked.json()["url"].startswith(f"{BOUND}/v1/runs/{RUN}/recording.rrd?")
    named = uploaded.client.post(
        f"/v1/runs/{RUN}/links", headers={**bearer(uploaded.token("read")), "Host": "localhost:8080"}
    )
    assert named.json()["url"].startswith(f"http://localhost:8080/v1/runs/{RUN}/recording.rrd?")


@pytest.mark.sdk
def test_the_consoles_links_never_name_the_host_a_client_sent(uploaded: Depot):
    client = log_in(uploaded.client, uploaded.token("read"))
    page = client.get(f"/console/runs/{RUN}/viewer", headers=FORGED)
    assert page.status_code == 200 and "evil" not in page.text
    command = re.search(r'rerun &#34;([^&]+)&#34;|rerun "([^"]+)"', page.text)
    assert command is not None, page.text
    assert (command.group(1) or command.group(2)).startswith(f"{BOUND}/v1/runs/{RUN}/recording.rrd?")
    data_url = re.search(r'data-url="([^"]+)"', page.text)
    assert data_url is not None and data_url.group(1).startswith(f"/v1/runs/{RUN}/recording.rrd?")

    download = client.get(f"/console/runs/{RUN}/download", headers=FORGED, follow_redirects=False)
    assert download.status_code == 303
    assert download.headers["location"].startswith(f"/v1/runs/{RUN}/recording.rrd?")
