"""A catalog outage with auth on does not stop ingest: `fleet serve` on a Postgres catalog reached
through a loopback proxy the test makes refuse or hang. A token the catalog confirmed before keeps
being accepted (FLEET_AUTH_STALE_S) and the real SDK's stream is filed; a token it never confirmed
is refused UNAVAILABLE, never INTERNAL; a hung catalog delays a token check by at most
`token_cache.WAIT_S`, never by the hang's length."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import httpx
import pytest
from sqlalchemy.engine import make_url

from services.auth.token_cache import WAIT_S
from tests.postgres import temporary_database
from tests.services.ingest.authed import AuthedDepot
from tests.services.ingest.live_server import LiveServer
from tests.services.ingest.test_sdk_tokens import LAST_FRAME, run_robot
from tests.services.retention.conftest import log_run
from tests.tcp_proxy import FORWARD, HANG, REFUSE, TcpProxy, tcp_proxy

pytestmark = [pytest.mark.postgres, pytest.mark.sdk]


@pytest.fixture
def outage(migrated_postgres_template: str, tmp_path: Path) -> Iterator[tuple[AuthedDepot, TcpProxy]]:
    with temporary_database("fleet_authed_outage", template=migrated_postgres_template) as url:
        parsed = make_url(url)
        with tcp_proxy(parsed.host or "127.0.0.1", parsed.port or 5432) as proxy:
            proxied = parsed.set(host="127.0.0.1", port=proxy.port).render_as_string(hide_password=False)
            live = LiveServer(
                tmp_path / "data",
                auth="on",
                auth_cache_s="0",  # every check asks the catalog: only the stale bound lets a token in
                catalog_url=proxied,
                catalog_flush_s="0.2",  # the scheduler's ownership pass claims the runs filed meanwhile
            ).start()
            try:
                yield AuthedDepot(live), proxy
            finally:
                proxy.set_mode(REFUSE)  # frees threads still waiting on a hung connection
                live.stop()


def checked(live: LiveServer, token: str) -> tuple[grpc.StatusCode, float]:
    """An empty SDK stream with `token`: its status and how long the answer took."""
    started = time.monotonic()
    status, _ = live.write_messages([], timeout=30, token=token)
    return status, time.monotonic() - started


def uploaded(depot: AuthedDepot, body: bytes, token: str) -> tuple[httpx.Response, float]:
    started = time.monotonic()
    answer = httpx.post(f"{depot.live.url}/v1/uploads", content=body, headers=depot.bearer(token), timeout=60)
    return answer, time.monotonic() - started


def test_uploads_go_on_with_auth_on_while_the_catalog_is_down_or_hung(
    outage: tuple[AuthedDepot, TcpProxy], tmp_path: Path
):
    depot, proxy = outage
    robot = depot.token("ingest", robot="robot-up")
    unconfirmed = depot.token("ingest", robot="robot-new")
    bodies = {n: log_run(tmp_path / f"{n}.rrd", n, frames=5, robot="robot-up").read_bytes() for n in ("a", "b", "c")}
    assert uploaded(depot, bodies["a"], robot.token)[0].json()["catalog"] == "updated"

    proxy.set_mode(REFUSE)
    answer, _ = uploaded(depot, bodies["b"], robot.token)
    assert answer.status_code == 200, answer.text  # kept; the catalog learns of it once it answers
    answer, _ = uploaded(depot, bodies["c"], unconfirmed.token)
    assert answer.status_code == 503 and answer.json()["code"] == "UNAVAILABLE", answer.text

    proxy.set_mode(HANG)
    answer, took = uploaded(depot, bodies["c"], robot.token)
    # the documented deadline: the catalog's part of an upload answer waits 10 s, a token check WAIT_S
    assert answer.status_code == 200 and took < 10 + WAIT_S + 3, (answer.text, took)

    proxy.set_mode(FORWARD)
    for run_id in ("b", "c"):
        assert depot.wait_for_run(run_id)["robot_id"] == "robot-up"


def test_sdk_streams_go_on_with_auth_on_while_the_catalog_is_down_or_hung(outage: tuple[AuthedDepot, TcpProxy]):
    depot, proxy = outage
    robot = depot.token("ingest", robot="robot-out")
    unconfirmed = depot.token("ingest", robot="robot-new")  # never used before the outage
    assert checked(depot.live, robot.token)[0] == grpc.StatusCode.OK  # the catalog confirms it once

    proxy.set_mode(REFUSE)  # the database is down
    assert "FLUSHED" in run_robot(depot, "down-run", "-", robot.token)
    assert checked(depot.live, unconfirmed.token)[0] == grpc.StatusCode.UNAVAILABLE

    proxy.set_mode(HANG)  # the database accepts connections and never answers
    for token, expected in ((robot.token, grpc.StatusCode.OK), (unconfirmed.token, grpc.StatusCode.UNAVAILABLE)):
        status, took = checked(depot.live, token)
        assert status == expected and took < WAIT_S + 2, (status, took)
    assert "FLUSHED" in run_robot(depot, "hung-run", "-", robot.token)

    proxy.set_mode(FORWARD)  # back: what was filed meanwhile reaches the catalog
    for run_id in ("down-run", "hung-run"):
        run = depot.wait_for_run(run_id, last_frame=LAST_FRAME)
        assert run["robot_id"] == "robot-out"
