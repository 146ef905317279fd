"""Who may stream runs in over gRPC, against a real `fleet serve` with auth on: a raw gRPC client
sends what the SDK's GrpcSink sends (recordings written by the real rerun-sdk), with a token in its
`authorization` metadata or in its fleet property, or none. Tokens listed in DuckDB and in Postgres."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import pytest

from services.rrd.pb import sdk_comms_pb2
from tests.conftest import CATALOG_KINDS
from tests.postgres import temporary_database
from tests.services.ingest.authed import AuthedDepot, chunks_in, recorded_requests
from tests.services.ingest.live_server import LiveServer

pytestmark = pytest.mark.sdk

WAIT_S = 3.0  # FLEET_AUTH_WAIT_S
BUFFER = 256 * 1024  # FLEET_AUTH_BUFFER_BYTES: about five frames of recorded_requests
READ_MESSAGES = "/rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages"


@pytest.fixture(scope="module", params=CATALOG_KINDS)
def depot(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[AuthedDepot]:
    """A depot whose tokens are listed in DuckDB or Postgres."""
    with contextlib.ExitStack() as stack:
        catalog = {}
        if request.param == "postgres":
            template = request.getfixturevalue("migrated_postgres_template")
            catalog["catalog_url"] = stack.enter_context(temporary_database("fleet_auth", template=template))
        live = LiveServer(
            tmp_path_factory.mktemp("stream-auth") / "data",
            auth="on",
            auth_wait_s=str(WAIT_S),
            auth_buffer_bytes=str(BUFFER),
            catalog_flush_s="0.2",
            durability="off",
            **catalog,
        ).start()
        stack.callback(live.stop)
        yield AuthedDepot(live)


def refused_quickly(started: float) -> bool:
    """Refused on the spot, not at the end of the wait for a token."""
    return time.monotonic() - started < WAIT_S


def test_an_ingest_token_in_metadata_files_the_run_under_its_robot(depot: AuthedDepot, tmp_path: Path):
    robot = depot.token("ingest", robot="robot-meta")
    requests = recorded_requests(tmp_path / "r.rrd", "meta-run")  # no fleet property at all
    assert depot.live.write_messages(requests, token=robot.token) == (grpc.StatusCode.OK, "")
    run = depot.wait_for_run("meta-run", chunks=chunks_in(requests))
    assert run["robot_id"] == "robot-meta"


def test_a_token_in_the_fleet_property_after_data_files_everything_held_in_order(depot: AuthedDepot, tmp_path: Path):
    robot = depot.token("ingest", robot="robot-late")
    requests = recorded_requests(tmp_path / "r.rrd", "late-run", token=robot.token, token_last=True)
    assert sum(map(len, requests)) < BUFFER
    assert depot.live.write_messages(requests) == (grpc.StatusCode.OK, "")
    run = depot.wait_for_run("late-run", chunks=chunks_in(requests))
    assert run["robot_id"] == "robot-late"
    assert "token" not in run["properties"]["fleet"]
    assert [t["min"] for t in run["timelines"] if t["name"] == "frame"] == [0]


def test_a_stream_without_any_token_is_refused_and_nothing_is_kept(depot: AuthedDepot, tmp_path: Path):
    before = depot.failures("stream", "missing")
    requests = recorded_requests(tmp_path / "r.rrd", "no-token-run", robot="robot-x")
    code, details = depot.live.write_messages(requests)
    assert code == grpc.StatusCode.UNAUTHENTICATED, details
    assert "the stream ended before any token" in details
    assert "fleet tokens create --scope ingest --robot ROBOT" in details and "token=TOKEN" in details
    assert depot.kept_nothing_of("no-token-run")
    assert depot.failures("stream", "missing") == before + 1


def test_a_token_past_the_buffer_limit_is_refused(depot: AuthedDepot, tmp_path: Path):
    robot = depot.token("ingest", robot="robot-big")
    requests = recorded_requests(tmp_path / "r.rrd", "big-run", token=robot.token, frames=8, token_last=True)
    assert sum(map(len, requests[:-1])) > BUFFER
    code, details = depot.live.write_messages(requests)
    assert code == grpc.StatusCode.UNAUTHENTICATED, details
    assert f"more than {BUFFER} bytes came before any token" in details
    assert depot.kept_nothing_of("big-run")


def test_a_silent_stream_is_refused_when_its_time_is_up(depot: AuthedDepot, tmp_path: Path):
    """Counted from the stream's start, while the client sends nothing more and keeps it open."""
    requests = recorded_requests(tmp_path / "r.rrd", "silent-run", frames=1)
    hang_up = threading.Event()

    def then_silence() -> Iterator[bytes]:
        yield from requests
        hang_up.wait(60)

    started = time.monotonic()
    try:
        code, details = depot.live.write_messages(then_silence())
    finally:
        hang_up.set()
    assert code == grpc.StatusCode.UNAUTHENTICATED, details
    assert WAIT_S <= time.monotonic() - started < WAIT_S + 10
    assert f"no token came within {WAIT_S:g} s of the stream's start" in details
    assert depot.kept_nothing_of("silent-run")


@pytest.mark.parametrize("how", ["metadata", "property"])
def test_revoked_and_expired_tokens_are_refused_at_once(depot: AuthedDepot, tmp_path: Path, how: str):
    revoked = depot.token("ingest", robot="robot-r")
    depot.revoke(revoked)
    expired = depot.token("ingest", robot="robot-r", expires_in_s=1)
    depot.live.wait_for(lambda: depot.get("/v1/whoami", expired.token).status_code == 401, what="the token expired")
    for made, reason, says in [(revoked, "revoked", "was revoked"), (expired, "expired", "has expired")]:
        run_id = f"{reason}-{how}-run"
        surface = "grpc" if how == "metadata" else "stream"
        before = depot.failures(surface, reason)
        in_property = made.token if how == "property" else "-"
        requests = recorded_requests(tmp_path / f"{reason}.rrd", run_id, robot="robot-r", token=in_property)
        started = time.monotonic()
        code, details = depot.live.write_messages(requests, token=made.token if how == "metadata" else None)
        assert code == grpc.StatusCode.UNAUTHENTICATED and says in details, (code, details)
        assert refused_quickly(started)
        assert depot.kept_nothing_of(run_id)
        assert depot.failures(surface, reason) == before + 1


@pytest.mark.parametrize("how", ["metadata", "property"])
def test_a_read_token_cannot_write(depot: AuthedDepot, tmp_path: Path, how: str):
    reader = depot.token("read")
    run_id = f"read-{how}-run"
    surface = "grpc" if how == "metadata" else "stream"
    before = depot.failures(surface, "forbidden")
    requests = recorded_requests(tmp_path / "r.rrd", run_id, token=reader.token if how == "property" else "-")
    started = time.monotonic()
    code, details = depot.live.write_messages(requests, token=reader.token if how == "metadata" else None)
    assert code == grpc.StatusCode.PERMISSION_DENIED, details
    assert "needs the 'ingest' or 'write' scope" in details
    assert refused_quickly(started)
    assert depot.kept_nothing_of(run_id)
    assert depot.failures(surface, "forbidden") == before + 1


def test_a_robot_token_cannot_write_another_robots_run(depot: AuthedDepot, tmp_path: Path):
    robot_a = depot.token("ingest", robot="robot-a")
    requests = recorded_requests(tmp_path / "r.rrd", "b-run", robot="robot-b", token=robot_a.token)
    code, details = depot.live.write_messages(requests)
    assert code == grpc.StatusCode.PERMISSION_DENIED, details
    assert "robot 'robot-b'" in details and "robot 'robot-a' only" in details
    assert depot.kept_nothing_of("b-run")


def test_a_write_token_streams_for_any_robot(depot: AuthedDepot, tmp_path: Path):
    writer = depot.token("write")
    requests = recorded_requests(tmp_path / "r.rrd", "written-run", robot="robot-w", token=writer.token)
    assert depot.live.write_messages(requests) == (grpc.StatusCode.OK, "")
    assert depot.wait_for_run("written-run", chunks=chunks_in(requests))["robot_id"] == "robot-w"


def read_first(depot: AuthedDepot, token: str | None) -> tuple[grpc.StatusCode, str, bytes]:
    """What ReadMessages answers with `token` (None: no metadata): its refusal, else its first message."""
    metadata = [("authorization", f"Bearer {token}")] if token else None
    with grpc.insecure_channel(f"127.0.0.1:{depot.live.grpc_port}") as channel:
        call = channel.unary_stream(READ_MESSAGES, request_serializer=None, response_deserializer=None)
        try:
            return grpc.StatusCode.OK, "", next(call(b"", timeout=30, metadata=metadata))
        except grpc.RpcError as exc:
            return exc.code(), exc.details() or "", b""  # type: ignore[attr-defined]


def test_read_messages_needs_a_read_token(depot: AuthedDepot, tmp_path: Path):
    robot = depot.token("ingest", robot="robot-live")
    requests = recorded_requests(tmp_path / "r.rrd", "watched-run", frames=1)
    hang_up = threading.Event()

    def live_stream() -> Iterator[bytes]:  # a run that stays live while it is read
        yield from requests
        hang_up.wait(60)

    writer = threading.Thread(target=depot.live.write_messages, args=(live_stream(),), kwargs={"token": robot.token})
    writer.start()
    try:
        depot.wait_for_run("watched-run", chunks=2)
        code, details, _ = read_first(depot, None)
        assert code == grpc.StatusCode.UNAUTHENTICATED and "no token" in details, (code, details)
        code, details, _ = read_first(depot, robot.token)
        assert code == grpc.StatusCode.PERMISSION_DENIED and "needs the 'read' scope" in details
        code, details, first = read_first(depot, depot.token("read").token)
        assert code == grpc.StatusCode.OK, details
        response = sdk_comms_pb2.ReadMessagesResponse.FromString(first)
        assert response.log_msg.set_store_info.info.store_id.recording_id == "watched-run"
    finally:
        hang_up.set()
        writer.join(60)
