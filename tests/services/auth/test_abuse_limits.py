"""Abuse limits over REST: SQL and downloads per token (429 with Retry-After; other tokens go on;
nothing counted with auth off), and every refused request counted in /metrics by surface and reason."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from services.auth.tokens import EXPIRED, FORBIDDEN, INVALID, MISSING, REVOKED
from tests.services.api.nodes import migrated_settings, node
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.rrd.recordings import Recording

RATES = {"sql_rate": "2/minute", "download_rate": "2/minute"}
QUERY = {"query": "SELECT count(*) AS runs FROM runs"}
RUN = "rec-points"


@pytest.fixture
def limited(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Depot]:
    with open_depot(tmp_path, fresh_catalog_url, **RATES) as opened:
        yield opened


def _limited(answer: httpx.Response, kind: str) -> None:
    assert answer.status_code == 429, answer.text
    assert 1 <= int(answer.headers["Retry-After"]) <= 60
    assert answer.json()["code"] == "RESOURCE_EXHAUSTED" and f"too many {kind} requests" in answer.json()["message"]


def test_sql_is_limited_per_token(limited: Depot):
    alice, bob = bearer(limited.token("read")), bearer(limited.token("read"))
    for _ in range(2):
        assert limited.client.post("/v1/sql", json=QUERY, headers=alice).status_code == 200
    _limited(limited.client.post("/v1/sql", json=QUERY, headers=alice), "sql")
    assert limited.client.post("/v1/sql", json=QUERY, headers=bob).status_code == 200  # another token goes on
    assert limited.client.get("/v1/runs", headers=alice).status_code == 200  # other reads are not limited


@pytest.mark.sdk
def test_downloads_are_limited_per_token_links_counting_against_the_token_that_signed_them(
    limited: Depot, scenes: dict[str, Recording]
):
    client = limited.client
    assert client.post("/v1/uploads", content=scenes["points"].data, headers=bearer(limited.token("write"))).is_success
    alice, bob = bearer(limited.token("read")), bearer(limited.token("read"))
    link = client.post(f"/v1/runs/{RUN}/links", headers=bob).json()["url"]
    for _ in range(2):
        assert client.get(f"/v1/runs/{RUN}/recording.rrd", headers=alice).status_code == 200
    _limited(client.get(f"/v1/runs/{RUN}/recording.rrd", headers=alice), "download")
    assert client.get(link).status_code == 200  # bob's share
    assert client.get(f"/v1/runs/{RUN}/recording.rrd", headers=bob).status_code == 200
    _limited(client.get(link), "download")


def test_nothing_is_limited_with_auth_off(tmp_path: Path):
    with node(migrated_settings(tmp_path, auth="off", **RATES)) as client:
        for _ in range(4):
            assert client.post("/v1/sql", json=QUERY).status_code == 200
            assert client.get(f"/v1/runs/{RUN}/recording.rrd").status_code == 404  # past the limit's check


def test_refusals_are_counted_by_surface_and_reason(depot: Depot):
    client = depot.client
    refusals = {
        MISSING: {},
        INVALID: bearer("not.a.token"),
        EXPIRED: bearer(depot.expired_token("read")),
        REVOKED: bearer(depot.revoked_token("read")),
        FORBIDDEN: bearer(depot.token("ingest", robot="robot-a")),
    }
    for reason, headers in refusals.items():
        before = depot.failures("rest", reason)
        assert client.get("/v1/runs", headers=headers).status_code in (401, 403)
        assert client.post("/v1/sql", json=QUERY, headers=headers).status_code in (401, 403)
        assert depot.failures("rest", reason) == before + 2, reason
    assert depot.failures("link", FORBIDDEN) == 0
    client.get(f"/v1/runs/{RUN}/recording.rrd?sig=00&expires=1&by=x")
    assert depot.failures("link", FORBIDDEN) == 1


def test_metrics_need_a_read_token(depot: Depot):
    assert depot.client.get("/metrics").status_code == 401
    assert "fleet_auth_failures_total" in depot.client.get("/metrics", headers=bearer(depot.token("read"))).text
