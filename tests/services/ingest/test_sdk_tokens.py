"""End to end with the real rerun-sdk, unmodified: a robot proves itself to an auth-on `fleet serve`
only by the token in its fleet property (`rr.send_property("fleet", rr.AnyValues(token=...))`). With
it the run is filed under the token's robot; without it nothing is kept; and the token itself is
never written anywhere nor served back."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.services.ingest.authed import AuthedDepot
from tests.services.ingest.live_server import LiveServer, start_robot
from tests.services.ingest.secrets_scan import places_holding

pytestmark = pytest.mark.sdk

LAST_FRAME = 9  # robot.py's `token` robot logs frames 0 to 9


def run_robot(depot: AuthedDepot, run_id: str, robot: str, token: str) -> str:
    """robot.py's `token` robot, to its end; what it printed."""
    proc = start_robot("token", depot.live.grpc_url, run_id, robot, token)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, err
    return out


@pytest.fixture(scope="module")
def depot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AuthedDepot]:
    live = LiveServer(
        tmp_path_factory.mktemp("sdk-tokens") / "data", auth="on", catalog_flush_s="0.2", scheduler="false"
    ).start()
    yield AuthedDepot(live)
    live.stop()


def test_a_robot_with_its_token_is_filed_under_the_tokens_robot_and_the_token_is_nowhere(tmp_path: Path):
    live = LiveServer(tmp_path / "data", auth="on", catalog_flush_s="0.2", scheduler="false").start()
    try:
        depot = AuthedDepot(live)
        robot = depot.token("ingest", robot="robot-sdk")
        secrets = (robot.token, robot.signature)
        assert "FLUSHED" in run_robot(depot, "sdk-run", "-", robot.token)  # no robot_id: the token names it
        run = depot.wait_for_run("sdk-run", last_frame=LAST_FRAME)
        assert run["robot_id"] == "robot-sdk"
        assert run["properties"]["fleet"] == {}  # its one field was the token
        hot = depot.hot_folder("sdk-run")
        assert hot.is_dir() and (hot / "robot").read_text() == "robot-sdk"
        assert depot.places_holding(*secrets) == []

        answers = [depot.get("/v1/runs/sdk-run"), depot.get("/v1/runs", robot="robot-sdk")]
        answers.append(depot.get("/v1/runs/sdk-run/recording.rrd"))
        promoted = httpx.post(f"{live.url}/v1/runs/sdk-run/promote", headers=depot.bearer(depot.admin), timeout=120)
        assert promoted.status_code == 200, promoted.text
        assert depot.wait_for_run("sdk-run")["tier"] == "warm"
        answers.append(depot.get("/v1/runs/sdk-run/recording.rrd"))  # now from the warm tier
        for answer in answers:
            assert answer.status_code == 200, answer.text
        assert all(len(a.content) > 50_000 for a in answers[2:])  # the run itself: ten frames of lidar points
        downloads = [tmp_path / "hot.rrd", tmp_path / "warm.rrd"]
        for path, answer in zip(downloads, answers[2:], strict=True):
            path.write_bytes(answer.content)
        assert places_holding(downloads, list(secrets), open_catalogs=False) == []
        assert not any(s.encode() in a.content for a in answers[:2] for s in secrets)
    finally:
        live.stop()
    assert depot.places_holding(*secrets, open_catalog=True) == []  # sealed objects, analytics, catalog rows


def test_a_robot_without_a_token_is_refused_and_nothing_is_kept(depot: AuthedDepot):
    before = depot.failures("stream", "missing")
    run_robot(depot, "tokenless-run", "robot-sdk", "-")
    depot.live.wait_for(lambda: depot.failures("stream", "missing") == before + 1, what="the stream refused")
    assert depot.kept_nothing_of("tokenless-run")
    assert "the stream ended before any token" in depot.live.log.read_text()


def test_a_robot_named_in_the_property_must_be_the_tokens(depot: AuthedDepot):
    robot = depot.token("ingest", robot="robot-one")
    run_robot(depot, "other-robot-run", "robot-two", robot.token)
    depot.live.wait_for(
        lambda: "this token writes for robot 'robot-one' only" in depot.live.log.read_text(), what="the refusal"
    )
    assert depot.kept_nothing_of("other-robot-run")


def test_a_run_keeps_its_tokens_robot_across_a_kill_and_restart(tmp_path: Path):
    live = LiveServer(tmp_path / "data", auth="on", catalog_flush_s="3600", scheduler="false").start()
    try:
        depot = AuthedDepot(live)
        robot = depot.token("ingest", robot="robot-kept")
        assert "FLUSHED" in run_robot(depot, "kept-run", "-", robot.token)
        live.wait_for(lambda: depot.metric("fleet_live_streams") == 0, what="the stream closed")
        # Not in the catalog yet (its list reads the catalog alone): only the hot folder knows its robot.
        assert "kept-run" not in {run["id"] for run in depot.get("/v1/runs").json()["runs"]}
        live.kill()
        live.start()
        run = depot.wait_for_run("kept-run", last_frame=LAST_FRAME)
        assert run["robot_id"] == "robot-kept"
    finally:
        live.stop()
