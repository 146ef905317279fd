"""A live run followed with auth on, against a real `fleet serve`: the stream stops when what let it
in ends, while the robot is still sending (a frame of about 48 KiB every 50 ms). A signed link with
follow=true stops at its expiry, and at the revocation of the token that signed it; a follow with
a bearer token, and a `ReadMessages` reader, stop when their token is revoked. The HTTP stream ends
with an End message: a recording that ended, which Rerun loads."""

from __future__ import annotations

import datetime as dt
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import grpc
import httpx
import pytest

from services.auth.standing import RECHECK_S
from services.rrd.frames import MessageKind, encode_message_header
from tests.services.ingest.authed import AuthedDepot, Made, recorded_requests
from tests.services.ingest.live_server import LiveServer

pytestmark = pytest.mark.sdk

READ_MESSAGES = "/rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages"
FRAMES = 200  # at 20 a second: the robot sends for 10 s, then keeps its stream (and the run) open
GAP_S = 0.05
# What may still arrive after the end: a check is due every RECHECK_S, plus what was in flight on
# a machine shared with other tests.
SLACK_S = RECHECK_S + 2.0


@pytest.fixture(scope="module")
def depot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AuthedDepot]:
    live = LiveServer(tmp_path_factory.mktemp("follow-auth") / "data", auth="on", durability="off").start()
    try:
        yield AuthedDepot(live)
    finally:
        live.stop()


class Robot:
    """A robot streaming a run (FRAMES frames recorded by the real SDK) with its ingest token: the
    first frames at once, then one every GAP_S, then its stream held open (the run stays live)
    until `hang_up`."""

    def __init__(self, depot: AuthedDepot, run_id: str, tmp_path: Path) -> None:
        self.requests = recorded_requests(tmp_path / f"{run_id}.rrd", run_id, frames=FRAMES)
        self.stop = threading.Event()
        token = depot.token("ingest", robot=f"robot-{run_id}").token
        self.thread = threading.Thread(
            target=depot.live.write_messages, args=(self._send(),), kwargs={"token": token, "timeout": 900}
        )
        self.thread.start()

    def _send(self) -> Iterator[bytes]:
        yield from self.requests[:6]
        for request in self.requests[6:]:
            if self.stop.wait(GAP_S):  # the robot's pace
                return
            yield request
        # Held until the test hangs up, however slow a loaded machine makes it (a stream that
        # ended on its own ends the run, which the tests check is still live).
        self.stop.wait(600)

    def hang_up(self) -> None:
        self.stop.set()
        self.thread.join(60)


@pytest.fixture
def live_run(depot: AuthedDepot, request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """The id of a run a robot is streaming now."""
    run_id = "follow-" + request.node.name.removeprefix("test_").replace("[", "-").rstrip("]")[-40:]
    robot = Robot(depot, run_id, tmp_path)
    try:
        depot.live.wait_for(lambda: depot.get(f"/v1/runs/{run_id}/recording.rrd").status_code == 200, what="live")
        yield run_id
    finally:
        robot.hang_up()


@dataclass
class Followed:
    """What a follower received, and when (monotonic seconds)."""

    pieces: list[tuple[float, int]] = field(default_factory=list)
    data: bytearray = field(default_factory=bytearray)
    ended_at: float | None = None
    first: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)

    def after(self, moment: float) -> int:
        return sum(n for at, n in self.pieces if at > moment)


def follow(url: str, headers: dict[str, str] | None = None) -> Followed:
    followed = Followed()

    def read() -> None:
        with httpx.stream("GET", url, headers=headers, timeout=120) as response:
            assert response.status_code == 200, response.read()
            for piece in response.iter_raw():
                followed.pieces.append((time.monotonic(), len(piece)))
                followed.data.extend(piece)
                followed.first.set()
        followed.ended_at = time.monotonic()
        followed.done.set()

    threading.Thread(target=read, daemon=True).start()
    assert followed.first.wait(60), "nothing arrived"
    return followed


def still_live(depot: AuthedDepot, run_id: str) -> bool:
    run = depot.run(run_id)
    return run is not None and run["status"] == "live"


def verified(data: bytes, tmp_path: Path, rerun_bin: str) -> None:
    """`data` is a whole recording that ended (its last message End; no footer, which is optional
    and, for a stream cut short, would describe only part of the run), which Rerun loads."""
    assert data.endswith(encode_message_header(MessageKind.END, 0))
    out = tmp_path / "followed.rrd"
    out.write_bytes(data)
    check = subprocess.run(
        [rerun_bin, "rrd", "verify", "--check-footers", "false", str(out)], capture_output=True, text=True
    )
    assert check.returncode == 0, check.stderr


def test_a_follow_link_stops_at_its_expiry(depot: AuthedDepot, live_run: str, tmp_path: Path, rerun_bin: str):
    run_id = live_run
    reader = depot.token("read")
    asked = httpx.post(
        f"{depot.live.url}/v1/runs/{run_id}/links",
        params={"follow": "true", "expires_in": "4"},
        headers=depot.bearer(reader.token),
        timeout=30,
    )
    assert asked.status_code == 200, asked.text
    expires_in = dt.datetime.fromisoformat(asked.json()["expires_at"]) - dt.datetime.now(dt.UTC)
    expired = time.monotonic() + expires_in.total_seconds()  # when the link expires, on this clock
    followed = follow(asked.json()["url"])
    assert followed.done.wait(30), "the link's stream went on past its expiry"
    assert followed.ended_at is not None and followed.ended_at - expired < SLACK_S
    late = followed.after(expired + SLACK_S)
    assert late == 0, f"{late} bytes after the expiry"
    assert still_live(depot, run_id)  # the robot still sends: the link ended, not the run
    verified(bytes(followed.data), tmp_path, rerun_bin)


@pytest.mark.parametrize("how", ["bearer", "link"])
def test_a_follow_stops_when_its_token_is_revoked(
    depot: AuthedDepot, live_run: str, how: str, tmp_path: Path, rerun_bin: str
):
    run_id = live_run
    reader = depot.token("read")
    if how == "bearer":
        followed = follow(f"{depot.live.url}/v1/runs/{run_id}/recording.rrd?follow=true", depot.bearer(reader.token))
    else:
        asked = httpx.post(
            f"{depot.live.url}/v1/runs/{run_id}/links",
            params={"follow": "true"},
            headers=depot.bearer(reader.token),
            timeout=30,
        )
        followed = follow(asked.json()["url"])
    depot.revoke(reader)
    revoked = time.monotonic()
    assert followed.done.wait(30), "the stream went on after its token was revoked"
    assert followed.ended_at is not None and followed.ended_at - revoked < SLACK_S
    assert followed.after(revoked + SLACK_S) == 0
    assert still_live(depot, run_id)
    verified(bytes(followed.data), tmp_path, rerun_bin)


@pytest.mark.usefixtures("live_run")
def test_a_read_messages_reader_stops_when_its_token_is_revoked(depot: AuthedDepot):
    reader: Made = depot.token("read")
    got: list[float] = []
    outcome: dict[str, object] = {}
    first = threading.Event()

    def read() -> None:
        with grpc.insecure_channel(f"127.0.0.1:{depot.live.grpc_port}") as channel:
            call = channel.unary_stream(READ_MESSAGES, request_serializer=None, response_deserializer=None)
            try:
                for _ in call(b"", timeout=60, metadata=[("authorization", f"Bearer {reader.token}")]):
                    got.append(time.monotonic())
                    first.set()
                outcome["code"] = grpc.StatusCode.OK
            except grpc.RpcError as exc:
                outcome["code"], outcome["details"] = exc.code(), exc.details()  # type: ignore[attr-defined]
            outcome["at"] = time.monotonic()

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    assert first.wait(60), "nothing arrived"
    depot.revoke(reader)
    revoked = time.monotonic()
    thread.join(30)
    assert not thread.is_alive(), "the reader went on after its token was revoked"
    assert outcome["code"] == grpc.StatusCode.UNAUTHENTICATED, outcome
    assert "revoked" in str(outcome["details"]) and float(outcome["at"]) - revoked < SLACK_S  # type: ignore[arg-type]
    assert not [at for at in got if at > revoked + SLACK_S]
