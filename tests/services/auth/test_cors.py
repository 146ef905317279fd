"""CORS: configured web origins call the API with a token; any other origin only reads by plain
GET (a signed link from the Rerun web viewer), never with a token and never a write."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.rrd.recordings import Recording

CONSOLE = "https://console.example"
ELSEWHERE = "https://elsewhere.example"
RUN = "rec-points"


@pytest.fixture
def depot(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    with open_depot(tmp_path, fresh_catalog_url, cors_origins=f"{CONSOLE}/") as opened:
        yield opened


def _preflight(depot: Depot, path: str, origin: str, method: str, headers: str | None) -> httpx.Response:
    asked = {"Origin": origin, "Access-Control-Request-Method": method}
    if headers is not None:
        asked["Access-Control-Request-Headers"] = headers
    answer: httpx.Response = depot.client.options(path, headers=asked)
    return answer


@pytest.mark.parametrize(("method", "path"), [("POST", f"/v1/runs/{RUN}/pin"), ("DELETE", f"/v1/runs/{RUN}")])
def test_a_configured_origin_may_send_a_token_to_any_endpoint(depot: Depot, method: str, path: str):
    answer = _preflight(depot, path, CONSOLE, method, "authorization, content-type")
    assert answer.status_code == 200, answer.text
    assert answer.headers["Access-Control-Allow-Origin"] == CONSOLE
    assert method in answer.headers["Access-Control-Allow-Methods"]
    assert "authorization" in answer.headers["Access-Control-Allow-Headers"].lower()
    real = depot.client.request(method, path, headers={"Origin": CONSOLE, **bearer(depot.token("admin"))})
    assert real.status_code == 404  # through to the route: no such run
    assert real.headers["Access-Control-Allow-Origin"] == CONSOLE


def test_a_configured_origin_still_needs_a_token(depot: Depot):
    answer = depot.client.get("/v1/runs", headers={"Origin": CONSOLE})
    assert answer.status_code == 401 and answer.headers["Access-Control-Allow-Origin"] == CONSOLE


@pytest.mark.parametrize(
    ("method", "headers"),
    [("POST", None), ("DELETE", None), ("POST", "authorization"), ("GET", "authorization"), ("GET", "x-fleet-user")],
)
def test_another_origin_may_not_write_or_send_a_token(depot: Depot, method: str, headers: str | None):
    answer = _preflight(depot, f"/v1/runs/{RUN}/pin", ELSEWHERE, method, headers)
    assert answer.status_code >= 400
    assert "Access-Control-Allow-Origin" not in answer.headers, answer.headers


def test_another_origin_gets_no_answer_to_a_write_it_sends_anyway(depot: Depot):
    """A form or a `no-cors` fetch skips the preflight: the write is refused before any route runs."""
    answer = depot.client.post(
        "/v1/uploads", content=b"RRF2", headers={"Origin": ELSEWHERE, "Content-Type": "text/plain"}
    )
    assert answer.status_code == 403 and "FLEET_CORS_ORIGINS" in answer.json()["message"], answer.text
    assert "Access-Control-Allow-Origin" not in answer.headers


def test_the_depots_own_pages_may_write(depot: Depot):
    """Swagger UI at /docs posts from the depot's own origin: not a cross-origin request."""
    answer = depot.client.post("/v1/uploads", headers={"Origin": "http://testserver"})
    assert answer.status_code == 401  # to the route's own check: a token is needed


@pytest.mark.sdk
def test_any_origin_may_open_a_signed_link(depot: Depot, scenes: dict[str, Recording]):
    uploaded = depot.client.post("/v1/uploads", content=scenes["points"].data, headers=bearer(depot.token("write")))
    assert uploaded.status_code == 200, uploaded.text
    url = depot.client.post(f"/v1/runs/{RUN}/links", headers=bearer(depot.token("read"))).json()["url"]
    preflight = _preflight(depot, url, ELSEWHERE, "GET", None)
    assert preflight.status_code == 200 and preflight.headers["Access-Control-Allow-Origin"] == "*"
    answer = depot.client.get(url, headers={"Origin": ELSEWHERE})
    assert answer.status_code == 200 and answer.content.startswith(b"RRF2")
    assert answer.headers["Access-Control-Allow-Origin"] == "*"
    assert "ETag" in answer.headers["Access-Control-Expose-Headers"]
