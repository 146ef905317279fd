"""Every route of the depot (REST and console, as `fleet serve` installs them), found from the app
itself: a path id the catalog cannot hold (a NUL, which Postgres cannot even compare; a space; a
quote; 129 characters; a non-ASCII letter) is 422 naming the parameter, never a 500 or a 404, on
DuckDB and Postgres. A route added later is in the list without anyone adding it."""

from __future__ import annotations

import html
import re
from collections.abc import Iterator
from dataclasses import dataclass
from urllib.parse import quote

import pytest
from fastapi.routing import iter_route_contexts

from services.console.app import install
from tests.conftest import CATALOG_KINDS, fresh_catalog
from tests.services.auth.conftest import Depot, bearer, open_depot

PARAMETER = re.compile(r"\{(\w+)\}")
BAD_IDS = ["run\x00id", "run id", "run'id", "r" * 129, "rün"]
ALERT = re.compile(r'role="alert">([^<]+)<')


@dataclass(frozen=True)
class Route:
    method: str
    path: str

    @property
    def parameters(self) -> list[str]:
        return PARAMETER.findall(self.path)

    def url(self, bad: str, where: str) -> str:
        """The route's URL with `bad` as parameter `where` and a valid id as every other."""
        return PARAMETER.sub(lambda m: quote(bad, safe="") if m.group(1) == where else "some-id", self.path)

    def __str__(self) -> str:
        return f"{self.method} {self.path}"


@pytest.fixture(scope="module", params=CATALOG_KINDS)
def depot(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Depot]:
    tmp_path = tmp_path_factory.mktemp("path-ids")
    with fresh_catalog(request.param, request, tmp_path) as url, open_depot(tmp_path, url) as opened:
        install(opened.app)  # the console's routes, as fleet serve adds them
        yield opened


def routes_with_ids(depot: Depot) -> list[Route]:
    found = set()
    for route in iter_route_contexts(depot.app.routes):
        for method in getattr(route.original_route, "methods", None) or ():
            if PARAMETER.search(str(route.path)):
                found.add(Route(method, str(route.path)))
    return sorted(found, key=str)


def test_the_routes_are_found_from_the_app(depot: Depot):
    found = {str(r) for r in routes_with_ids(depot)}
    # a few of every kind, so the list cannot be empty or miss a router
    for known in (
        "GET /v1/runs/{run_id}",
        "GET /v1/runs/{run_id}/recording.rrd",
        "DELETE /v1/tokens/{token_id}",
        "POST /v1/pulls/{pull_id}/cancel",
        "GET /v1/queries/{query_id}",
        "GET /console/runs/{run_id}",
        "GET /console/viewer-assets/{version}/{name}",
    ):
        assert known in found
    assert len(found) >= 30


def test_every_path_id_the_catalog_cannot_hold_is_422_naming_it(depot: Depot):
    admin = bearer(depot.token("admin"))
    for route in routes_with_ids(depot):
        for where in route.parameters:
            for bad in BAD_IDS:
                answer = depot.client.request(route.method, route.url(bad, where), headers=admin)
                assert answer.status_code == 422, (str(route), where, bad, answer.status_code, answer.text[:300])
                if route.path.startswith("/console/"):  # shown as the console's error page
                    said = ALERT.search(answer.text)
                    assert said is not None, (str(route), answer.text[:300])
                    message = html.unescape(said.group(1))
                else:
                    assert answer.json()["code"] == "INVALID_ARGUMENT"
                    message = answer.json()["message"]
                assert f"parameter '{where}'" in message and "is not an id of this depot" in message, message
                assert "A-Z a-z 0-9 . _ -" in message


def test_an_id_of_the_right_form_still_reaches_the_route(depot: Depot):
    answer = depot.client.get("/v1/runs/no-such-run", headers=bearer(depot.token("read")))
    assert answer.status_code == 404 and "no-such-run" in answer.json()["message"]
