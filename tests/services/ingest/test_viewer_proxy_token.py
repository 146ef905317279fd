"""The real Rerun 0.41 viewer on the depot's message proxy: `rerun --connect
rerun+http://HOST:PORT/proxy`, which calls `ReadMessages`.

What it does, checked from the depot's side: the 0.41 viewer sends no `authorization` metadata on
`ReadMessages`, even with a valid read token in REDAP_TOKEN (a JWT whose `allowed_hosts` names the
depot's host), although the same viewer sends that token to the catalog service on the same port.
An auth-on depot therefore refuses the live view (UNAUTHENTICATED, counted in
`fleet_auth_failures_total{surface="grpc",reason="missing"}`), and the viewer does not try again:
a run streamed afterwards never reaches it. With auth off the same viewer follows a live run."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import grpc
import jwt
import pytest

from services.auth.metadata import GRPC
from services.auth.tokens import MISSING
from tests.services.ingest.authed import AuthedDepot
from tests.services.ingest.live_server import LiveServer, start_robot
from tests.viewer import HeadlessViewer, Server, assert_not_blank

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

READ_MESSAGES = "/rerun.sdk_comms.v1alpha1.MessageProxyService/ReadMessages"
RUN = "viewer-live-run"
ROBOT = "robot-viewer"
LAST_FRAME = 9  # robot.py's `token` robot logs frames 0 to 9
ROBOT_ENTITIES = {"/world/robot", "/world/robot/lidar", "/world/robot/camera", "/robot/battery", "/robot/log"}


def read_messages(port: int, token: str) -> grpc.StatusCode:
    """How a ReadMessages call with `token` ends when nothing is streaming: DEADLINE_EXCEEDED if the
    depot took it (it waits for live data), UNAUTHENTICATED if it refused it."""
    with grpc.insecure_channel(f"127.0.0.1:{port}") as channel:
        call = channel.unary_stream(READ_MESSAGES, request_serializer=None, response_deserializer=None)
        try:
            for _ in call(b"", timeout=2, metadata=[("authorization", f"Bearer {token}")]):
                pass
        except grpc.RpcError as exc:
            return exc.code()  # type: ignore[attr-defined, no-any-return]
    return grpc.StatusCode.OK


def stream_run(live: LiveServer, robot: str = "-", token: str = "-") -> None:
    """robot.py's `token` robot (the real SDK's GrpcSink) streams RUN into the depot, to its end."""
    proc = start_robot("token", live.grpc_url, RUN, robot, token)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0 and "FLUSHED" in out, err


def test_the_viewer_sends_no_token_on_read_messages_so_an_auth_on_depot_refuses_it(tmp_path: Path, rerun_bin: str):
    started = time.monotonic()
    live = LiveServer(tmp_path / "data", auth="on", catalog_flush_s="0.2", scheduler="false").start()
    try:
        depot = AuthedDepot(live)
        read = depot.token("read")
        claims = jwt.decode(read.token, options={"verify_signature": False})
        assert "127.0.0.1" in claims["allowed_hosts"]  # so Rerun's clients may send it to this depot
        assert read_messages(live.grpc_port, read.token) == grpc.StatusCode.DEADLINE_EXCEEDED  # it may read
        refused = depot.failures(GRPC, MISSING)

        env = {"REDAP_TOKEN": read.token}
        with HeadlessViewer(rerun_bin, tmp_path / "viewer", env=env, connect=live.grpc_url) as viewer:
            # The viewer's ReadMessages carries no token: refused, counted, and told to the user.
            live.wait_for(lambda: depot.failures(GRPC, MISSING) == refused + 1, 30, "the viewer's call refused")
            told = viewer.wait_until(
                lambda: [e for e in viewer.errors() if live.grpc_url in e], "the viewer to report the refusal"
            ).value
            assert "(Unauthenticated)" in told[0]  # the status the depot answered, as the viewer shows it

            # A run streamed now is filed by the depot but never reaches the viewer: it did not call again.
            stream_run(live, token=depot.token("ingest", robot=ROBOT).token)
            depot.wait_for_run(RUN, last_frame=LAST_FRAME)
            assert viewer.snapshot().state.recordings == []

            # The same viewer does send REDAP_TOKEN, to the catalog service on the same port.
            origin = live.grpc_url.removesuffix("/proxy")
            viewer.open(f"{origin}/catalog")

            def answered() -> Server | None:
                server = viewer.snapshot().server(origin)
                return server if server is not None and (server.error or server.entries) else None

            server = viewer.wait_until(answered, "the catalog service's answer").value
            assert "Unauthenticated" not in (server.error or "")
            assert depot.failures(GRPC, MISSING) == refused + 1
    finally:
        live.stop()
    print(f"viewer on an auth-on depot's message proxy: {time.monotonic() - started:.1f} s")


def test_with_auth_off_the_viewer_follows_a_live_run_on_the_message_proxy(tmp_path: Path, rerun_bin: str):
    started = time.monotonic()
    live = LiveServer(tmp_path / "data", auth="off", catalog_flush_s="0.2", scheduler="false").start()
    try:
        with HeadlessViewer(rerun_bin, tmp_path / "viewer", connect=live.grpc_url) as viewer:
            stream_run(live)

            def followed() -> Any | None:
                recording = viewer.snapshot().recording(RUN)
                frames = [t.end for t in recording.timelines if t.name == "frame"] if recording else []
                return recording if frames == [LAST_FRAME] else None

            recording = viewer.wait_until(followed, f"the viewer to show {RUN} up to frame {LAST_FRAME}").value
            schema = viewer.client.get_recording_schema(recording.store_id, paths_only=True)
            assert {e.entity_path for e in schema.entities} >= ROBOT_ENTITIES
            assert viewer.errors() == []
            assert_not_blank(viewer.screenshot("live-run"))
    finally:
        live.stop()
    print(f"viewer on an auth-off depot's message proxy: {time.monotonic() - started:.1f} s")
