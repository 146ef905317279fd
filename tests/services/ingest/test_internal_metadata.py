"""What only another node of the depot may say of a WriteMessages call (`fleet-source`,
`fleet-relayed-by`, `fleet-peer`): a client sending it through the public port is refused, so it
neither files token-less streams as uploads outside FLEET_MAX_STREAMS nor keeps a node from
relaying a stream to its run's owner. And what all streams waiting for their token hold together
stays within FLEET_AUTH_BUFFER_TOTAL_BYTES. Against a real `fleet serve`, auth on."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import AsyncIterator, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import grpc
import pytest

from core.errors import ResourceExhaustedError, UnauthenticatedError
from services.auth.tokens import Auth
from services.ingest.stream_auth import Admitted, CallAuth
from services.rrd.messages import Event
from tests.services.ingest.authed import AuthedDepot, recorded_requests
from tests.services.ingest.live_server import WRITE_MESSAGES, LiveServer
from tests.waiting import wait_for_async

pytestmark = pytest.mark.sdk

WAIT_S = 30.0  # FLEET_AUTH_WAIT_S: long, so a stream held until then shows as a timeout here
MAX_STREAMS = 2
TOTAL = 64 * 1024  # FLEET_AUTH_BUFFER_TOTAL_BYTES: less than one recording's first frames


@pytest.fixture(scope="module")
def depot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AuthedDepot]:
    live = LiveServer(
        tmp_path_factory.mktemp("internal") / "data",
        auth="on",
        auth_wait_s=str(WAIT_S),
        auth_buffer_total_bytes=str(TOTAL),
        max_streams=str(MAX_STREAMS),
        durability="off",
    ).start()
    try:
        yield AuthedDepot(live)
    finally:
        live.stop()


def held_open(live: LiveServer, requests: list[bytes], metadata: list[tuple[str, str]], hang_up: threading.Event):
    """One WriteMessages call that sends `requests` and then stays open until `hang_up`: its status."""

    def then_wait() -> Iterator[bytes]:
        yield from requests
        hang_up.wait(60)

    with grpc.insecure_channel(f"127.0.0.1:{live.grpc_port}") as channel:
        call = channel.stream_unary(WRITE_MESSAGES, request_serializer=None, response_deserializer=None)
        try:
            call(then_wait(), timeout=10, metadata=metadata)
        except grpc.RpcError as exc:
            return exc.code(), exc.details() or ""  # type: ignore[attr-defined]
    return grpc.StatusCode.OK, ""


def test_a_client_calling_its_streams_uploads_gets_no_way_past_the_stream_limit(depot: AuthedDepot, tmp_path: Path):
    """Token-less streams marked `fleet-source: upload` were held outside FLEET_MAX_STREAMS (100 of
    them held 1.6 GB): now each is refused at once, and none is held."""
    requests = recorded_requests(tmp_path / "r.rrd", "upload-claim", frames=1)[:1]
    hang_up = threading.Event()
    streams = MAX_STREAMS + 3
    with ThreadPoolExecutor(streams) as pool:
        started = time.monotonic()
        calls = [
            pool.submit(held_open, depot.live, requests, [("fleet-source", "upload")], hang_up) for _ in range(streams)
        ]
        try:
            answers = [c.result(timeout=60) for c in calls]
        finally:
            hang_up.set()
    assert all(code == grpc.StatusCode.UNAUTHENTICATED for code, _ in answers), answers
    assert all("fleet-source" in details and "client may not send" in details for _, details in answers)
    assert time.monotonic() - started < 8  # refused at once, not held until the token's time is up
    assert depot.live.metric("fleet_live_streams") == 0


def test_a_client_saying_another_node_relays_it_is_refused(depot: AuthedDepot, tmp_path: Path):
    """`fleet-relayed-by` would make the node file the stream itself rather than relay it to its run's
    owner (and answer it as to a node): refused, even with a valid token."""
    robot = depot.token("ingest", robot="robot-relay")
    requests = recorded_requests(tmp_path / "r.rrd", "relay-claim", frames=1)
    metadata = [("authorization", f"Bearer {robot.token}"), ("fleet-relayed-by", "some-node")]
    code, details = held_open(depot.live, requests, metadata, _set())
    assert code == grpc.StatusCode.UNAUTHENTICATED, details
    assert "fleet-relayed-by" in details
    # nor does a token of this depot make it so: a node proves itself with its peer token
    metadata.append(("fleet-peer", robot.token))
    code, details = held_open(depot.live, requests, metadata, _set())
    assert code == grpc.StatusCode.UNAUTHENTICATED, details
    assert depot.kept_nothing_of("relay-claim")


def test_streams_waiting_for_their_token_hold_at_most_the_total_budget(depot: AuthedDepot, tmp_path: Path):
    requests = recorded_requests(tmp_path / "r.rrd", "over-budget", frames=3)
    assert sum(map(len, requests)) > TOTAL  # within FLEET_AUTH_BUFFER_BYTES (16 MiB), beyond the total
    code, details = held_open(depot.live, requests, [], _set())
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, details
    assert "FLEET_AUTH_BUFFER_TOTAL_BYTES" in details
    assert depot.kept_nothing_of("over-budget")


def _set() -> threading.Event:
    done = threading.Event()
    done.set()
    return done


def test_many_token_less_streams_never_hold_more_than_the_total_together() -> None:
    """Measured: 200 streams of four 1 MiB requests, none with a token, read at once (200 x 16 MiB
    FLEET_AUTH_BUFFER_BYTES would allow 3.2 GB): what they hold together peaks at the total."""
    total, per_stream, request, streams = 8 << 20, 16 << 20, 1 << 20, 200
    calls = CallAuth(Auth(enabled=False, keys=None, catalog=None), wait_s=5, buffer_bytes=per_stream, total_bytes=total)
    gate = asyncio.Event()
    waiting = 0

    async def stream() -> AsyncIterator[bytes]:
        nonlocal waiting
        for _ in range(4):
            yield bytes(request)
        waiting += 1
        await gate.wait()  # held open, its token never sent

    def decode(raw: bytes, offset: int) -> Event:
        return None  # type: ignore[return-value]  # not a chunk: nothing in it is a token

    async def main() -> list[BaseException | Admitted]:
        tasks = [asyncio.create_task(calls.await_property_token(stream(), decode)) for _ in range(streams)]
        await wait_for_async(
            lambda: sum(t.done() for t in tasks) + waiting >= streams, 60, "every stream refused or held"
        )
        assert 0 < calls.held.used <= total
        gate.set()
        return await asyncio.gather(*tasks, return_exceptions=True)

    outcomes = asyncio.run(main())
    assert calls.held.peak <= total and calls.held.used == 0
    refused = [o for o in outcomes if isinstance(o, ResourceExhaustedError)]
    assert len(refused) >= streams - total // request
    assert all(isinstance(o, ResourceExhaustedError | UnauthenticatedError) for o in outcomes)
