"""A download of a hot run whose owner is down: the catalog knows the run and its owner, so the node
asked answers 503 naming that node and its address (the data is there, on it), not 404 "no run".
Two real `fleet serve` processes on one Postgres catalog, auth on; the owner killed."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from tests.conftest import fresh_catalog
from tests.services.cluster.two_nodes import bearer, node, recording, requests_of, token

pytestmark = [pytest.mark.slow, pytest.mark.sdk, pytest.mark.postgres]


def test_a_run_whose_owner_is_down_is_unavailable_naming_its_owner(request: pytest.FixtureRequest, tmp_path: Path):
    with fresh_catalog("postgres", request, tmp_path) as url:
        a = node(tmp_path, "a", url, promote_after_s="3600").start()  # the run stays hot on A
        b = node(tmp_path, "b", url, promote_after_s="3600").start()
        try:
            robot, reader = token(a, ["ingest"], "r1"), token(a, ["read"])
            assert a.write_messages(requests_of(recording(tmp_path, "run-d", 20)), token=robot)[0].name == "OK"

            def b_says(path: str) -> httpx.Response:
                return httpx.get(f"{b.url}{path}", headers=bearer(reader), timeout=10)

            b.wait_for(lambda: b_says("/v1/runs/run-d").json().get("owner") == "a", what="the run owned by A")
            (peer_addr,) = [n["peer_addr"] for n in b_says("/v1/nodes").json()["nodes"] if n["id"] == "a"]
            a.kill()
            b.wait_for(
                lambda: not any(n["alive"] for n in b_says("/v1/nodes").json()["nodes"] if n["id"] == "a"),
                what="A's lease to run out (FLEET_LEASE_S)",
            )

            answer = b_says("/v1/runs/run-d/recording.rrd")
            assert answer.status_code == 503, answer.text
            body = answer.json()
            assert body["code"] == "UNAVAILABLE" and body["owner"] == "a" and body["owner_addr"] == peer_addr
            assert "node a" in body["message"] and peer_addr in body["message"]
            assert answer.headers["Retry-After"]
            # a run nobody knows is still 404
            assert b_says("/v1/runs/no-such-run/recording.rrd").status_code == 404
        finally:
            a.kill()
            b.kill()
