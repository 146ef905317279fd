"""Every REST route in one table: no token, a malformed, revoked or expired one -> 401 with a
challenge; a token without the scope -> 403 naming it; with it -> neither. A route added without
an entry here (or in the short list of open pages) fails the suite."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import pytest
from fastapi.routing import iter_route_contexts

from services.auth.scopes import Principal, Scope
from tests.conftest import CATALOG_KINDS, fresh_catalog
from tests.services.auth.conftest import Depot, bearer, open_depot

RUN = "no-such-run"
READ, WRITE, ADMIN, INGEST = Scope.READ, Scope.WRITE, Scope.ADMIN, Scope.INGEST

# Open to anyone: liveness, readiness, the API's docs and their assets (served by this process).
OPEN = {
    ("GET", "/healthz"),
    ("GET", "/readyz"),
    ("GET", "/docs"),
    ("GET", "/docs/oauth2-redirect"),
    ("GET", "/redoc"),
    ("GET", "/openapi.json"),
    ("HEAD", "/openapi.json"),
    ("MOUNT", "/static-offline-docs"),
}


@dataclass(frozen=True)
class Guarded:
    method: str
    path: str
    scopes: tuple[Scope, ...]  # any one of them lets the request in
    body: dict[str, Any] = field(default_factory=dict)  # httpx keywords of a request that gets past auth

    @property
    def url(self) -> str:
        return (
            self.path.replace("{run_id}", RUN)
            .replace("{token_id}", "no-such-token")
            .replace("{pull_id}", "no-such-pull")
            .replace("{query_id}", "no-such-query")
            .replace("{event_id}", "no-such-event")
            .replace("{webhook_id}", "wh-000000000000")
            .replace("{name}", "no-such-dataset")
            .replace("{version}", "1")
            .replace("{episode}", "0")
            .replace("{job_id}", "exp-000000000000")
            .replace("{import_id}", "imp-000000000000")
        )

    def __str__(self) -> str:
        return f"{self.method} {self.path}"


TABLE = [
    Guarded("GET", "/v1/whoami", tuple(Scope)),
    Guarded("POST", "/v1/tokens", (ADMIN,), {"json": {"scopes": ["read"], "name": "from the table"}}),
    Guarded("GET", "/v1/tokens", (ADMIN,)),
    Guarded("DELETE", "/v1/tokens/{token_id}", (ADMIN,)),
    Guarded("POST", "/v1/sql", (READ,), {"json": {"query": "SELECT 1 AS one"}}),
    Guarded("POST", "/v1/runs/{run_id}/analytics", (WRITE,)),
    Guarded("GET", "/v1/queries", (READ,)),
    Guarded("POST", "/v1/queries", (WRITE,), {"json": {"name": "from the table", "sql": "SELECT 1 AS one"}}),
    Guarded("GET", "/v1/queries/{query_id}", (READ,)),
    Guarded("DELETE", "/v1/queries/{query_id}", (WRITE,)),
    Guarded("GET", "/v1/retention", (READ,)),
    Guarded("GET", "/v1/retention/plan", (READ,)),
    Guarded("POST", "/v1/retention/run", (ADMIN,)),
    Guarded("POST", "/v1/runs/{run_id}/pin", (WRITE,)),
    Guarded("DELETE", "/v1/runs/{run_id}/pin", (WRITE,)),
    Guarded("POST", "/v1/runs/{run_id}/promote", (WRITE,)),
    Guarded("POST", "/v1/runs/{run_id}/restore", (WRITE,)),
    Guarded("DELETE", "/v1/runs/{run_id}", (ADMIN,)),
    Guarded("POST", "/v1/catalog/rebuild", (ADMIN,)),
    Guarded("POST", "/v1/catalog/scrub-secrets", (ADMIN,), {"params": {"dry_run": "true"}}),
    Guarded("POST", "/v1/uploads", (INGEST, WRITE)),
    Guarded("GET", "/v1/imports", (READ,)),
    Guarded("GET", "/v1/imports/{import_id}", (READ,)),
    Guarded("POST", "/v1/imports/{import_id}/retry", (WRITE,)),
    Guarded("GET", "/v1/imports/{import_id}/original", (ADMIN,)),
    Guarded("GET", "/v1/robots", (READ,)),
    Guarded("GET", "/v1/nodes", (READ,)),
    Guarded("GET", "/v1/runs", (READ,)),
    Guarded("GET", "/v1/runs/{run_id}", (READ,)),
    Guarded("GET", "/v1/runs/{run_id}/recording.rrd", (READ,)),
    Guarded("POST", "/v1/runs/{run_id}/links", (READ,)),
    Guarded("GET", "/metrics", (READ,)),
    Guarded("POST", "/v1/runs/{run_id}/held", (INGEST, READ), {"json": {"chunk_ids": ["0" * 32]}}),
    Guarded("POST", "/v1/runs/{run_id}/pull", (WRITE,), {"json": {}}),
    Guarded("GET", "/v1/runs/{run_id}/pulls", (READ,)),
    Guarded("GET", "/v1/pulls", (INGEST, READ)),
    Guarded(
        "POST",
        "/v1/pulls/{pull_id}/progress",
        (INGEST, WRITE),
        {"json": {"state": "sending", "chunks_sent": 0, "bytes_sent": 0}},
    ),
    Guarded("POST", "/v1/pulls/{pull_id}/cancel", (WRITE,)),
    Guarded("PUT", "/v1/runs/{run_id}/robot-copy", (INGEST, ADMIN), {"json": {"chunks": 0, "bytes": 0}}),
    Guarded("DELETE", "/v1/runs/{run_id}/robot-copy", (INGEST, ADMIN)),
    Guarded("PUT", "/v1/rules", (WRITE,), {"content": ""}),  # no content type: 422, nothing applied
    Guarded("GET", "/v1/rules", (INGEST, READ)),  # a robot's agent runs the triggers
    Guarded("POST", "/v1/runs/{run_id}/triggered", (INGEST, WRITE), {"json": {}}),
    Guarded("POST", "/v1/events/{event_id}/pull", (WRITE,)),
    Guarded("GET", "/v1/rules/history", (READ,)),
    Guarded("POST", "/v1/rules/backfill", (WRITE,)),
    Guarded("GET", "/v1/events", (READ,)),
    Guarded("GET", "/v1/events/{event_id}", (READ,)),
    Guarded("GET", "/v1/runs/{run_id}/events", (READ,)),
    Guarded("POST", "/v1/runs/{run_id}/events", (WRITE,), {"json": {"timeline": "log_time", "start": 0}}),
    Guarded("POST", "/v1/runs/{run_id}/tags", (WRITE,), {"json": {"tags": ["a"]}}),
    Guarded("DELETE", "/v1/runs/{run_id}/tags", (WRITE,), {"params": {"tag": "a"}}),
    Guarded("POST", "/v1/webhooks", (ADMIN,), {"json": {"url": "https://hooks.example/", "on": ["run.sealed"]}}),
    Guarded("GET", "/v1/webhooks", (ADMIN,)),
    Guarded("DELETE", "/v1/webhooks/{webhook_id}", (ADMIN,)),
    Guarded("GET", "/v1/webhooks/{webhook_id}/deliveries", (ADMIN,)),
    Guarded("POST", "/v1/datasets", (WRITE,), {"json": {"name": "from-the-table"}}),
    Guarded("GET", "/v1/datasets", (READ,)),
    Guarded("GET", "/v1/datasets/{name}", (READ,)),
    Guarded("GET", "/v1/datasets/{name}/{version}", (READ,)),
    Guarded("GET", "/v1/datasets/{name}/{version}/episodes/{episode}/recording.rrd", (READ,)),
    Guarded("POST", "/v1/exports", (WRITE,), {"json": {"dataset": "a@1", "to": "s3://b/c"}}),
    Guarded("GET", "/v1/exports", (READ,)),
    Guarded("GET", "/v1/exports/{job_id}", (READ,)),
    Guarded("DELETE", "/v1/exports/{job_id}", (WRITE,)),
]


@dataclass
class Tokens:
    """One token per scope, and the kinds that must be refused."""

    depot: Depot
    by_scope: dict[Scope, str]
    revoked: str
    expired: str


@pytest.fixture(scope="module", params=CATALOG_KINDS)
def tokens(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Tokens]:
    """One depot per catalog kind for the whole table (nothing here changes what another row sees)."""
    tmp_path = tmp_path_factory.mktemp("routes")
    with fresh_catalog(request.param, request, tmp_path) as url, open_depot(tmp_path, url) as depot:
        by_scope = {s: depot.token(s.value, robot="robot-a" if s == INGEST else None) for s in Scope}
        yield Tokens(depot, by_scope, depot.revoked_token("admin"), depot.expired_token("admin"))


def _routes(depot: Depot) -> set[tuple[str, str]]:
    found = set()
    for route in iter_route_contexts(depot.app.routes):
        methods = getattr(route.original_route, "methods", None) or {"MOUNT"}
        found |= {(m, str(route.path)) for m in methods}
    return found


def test_every_route_is_guarded_or_open_on_purpose(tokens: Tokens):
    routes = _routes(tokens.depot)
    table = {(g.method, g.path) for g in TABLE}
    unlisted = routes - table - OPEN
    assert not unlisted, f"routes in neither the auth table nor the open list: {sorted(unlisted)}"
    assert not (table | OPEN) - routes, f"listed routes the app does not have: {sorted((table | OPEN) - routes)}"


@pytest.mark.parametrize("path", sorted({p for m, p in OPEN if m == "GET"}))
def test_open_pages_need_no_token(tokens: Tokens, path: str):
    assert tokens.depot.client.get(path).status_code == 200


def _call(tokens: Tokens, route: Guarded, headers: dict[str, str] | None = None) -> Any:
    return tokens.depot.client.request(route.method, route.url, headers=headers or {}, **route.body)


def _unauthenticated(response: Any, says: str) -> None:
    assert response.status_code == 401, response.text
    assert response.headers["WWW-Authenticate"].startswith("Bearer")
    assert response.json()["code"] == "UNAUTHENTICATED" and says in response.json()["message"]


@pytest.mark.parametrize("route", TABLE, ids=str)
def test_a_request_without_a_valid_token_is_401(tokens: Tokens, route: Guarded):
    _unauthenticated(_call(tokens, route), "no token")
    _unauthenticated(_call(tokens, route, {"Authorization": "Bearer"}), "no token")
    _unauthenticated(_call(tokens, route, {"Authorization": "Basic YWxpY2U6cHc="}), "no token")
    _unauthenticated(_call(tokens, route, bearer("not.a.token")), "not a valid token")
    _unauthenticated(_call(tokens, route, bearer(tokens.by_scope[ADMIN][:-3])), "not a valid token")
    _unauthenticated(_call(tokens, route, bearer(tokens.revoked)), "was revoked")
    _unauthenticated(_call(tokens, route, bearer(tokens.expired)), "has expired")


@pytest.mark.parametrize("route", TABLE, ids=str)
def test_a_token_is_let_in_only_with_a_scope_the_route_needs(tokens: Tokens, route: Guarded):
    named = " or ".join(f"'{s.value}'" for s in route.scopes)
    for scope, token in tokens.by_scope.items():
        response = _call(tokens, route, bearer(token))
        granted = Principal("x", frozenset({scope})).allows
        if any(granted(s) for s in route.scopes):
            assert response.status_code not in (401, 403), (scope, response.text)
        else:
            assert response.status_code == 403, (scope, response.text)
            assert response.json()["code"] == "PERMISSION_DENIED"
            assert f"needs the {named} scope" in response.json()["message"], response.text
