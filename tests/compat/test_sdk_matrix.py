"""Every supported rerun-sdk streams (live gRPC) and uploads into a real `fleet serve`; what the
depot serves equals the robot's copy and passes the newest `rerun rrd verify` (footers checked),
while the run is hot and after it is sealed. rerun-sdk 0.22 is told to upgrade, on both paths.

The depot runs with auth on: each robot has an ingest token of its own, sends it in its `fleet`
property (the stream's only credential) and uploads with it; the token is in no served byte nor
in the run's properties, for every SDK (0.23 writes `rerun.component`, not `rerun:component`).

Each SDK runs from its own venv (tests/compat/sdk_venvs.py, cached outside the clone); the pinned
SDK is this project's own. All robots run at once against one server, then the checks run at
once, so the matrix costs about as much as its slowest SDK.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest

from services.ingest.grpc_handler import LEGACY_REFUSAL
from tests.compat.sdk_venvs import LEGACY, MATRIX, PINNED, sdk_bin
from tests.compat.stripped import stripped_copy
from tests.services.ingest.authed import AuthedDepot
from tests.services.ingest.live_server import LiveServer
from tests.services.ingest.secrets_scan import places_holding

pytestmark = [pytest.mark.sdk, pytest.mark.slow]

VERSIONS = MATRIX
ROBOT = str(Path(__file__).with_name("robot.py"))
# Each log call its own chunk: a robot without set_sinks logs twice (gRPC, file), and both copies
# then hold the same chunks.
ROBOT_ENV = {**os.environ, "RERUN_FLUSH_NUM_ROWS": "1"}


def sdk_python(version: str) -> str:
    return sys.executable if version == PINNED else str(sdk_bin(version, "python"))


@dataclass
class Robot:
    version: str
    live_copy: Path
    upload_copy: Path
    token: str = field(default="", repr=False)  # its ingest token, sent in its fleet property
    upload_answer: dict[str, Any] = field(default_factory=dict)
    error: str | None = None  # what went wrong on the robot's side (the matrix goes on for others)

    @property
    def live_run(self) -> str:
        return f"live-{self.version}"

    @property
    def upload_run(self) -> str:
        return f"upload-{self.version}"

    @property
    def robot_id(self) -> str:
        return f"robot-{self.version.replace('.', '-')}"


def _run(cmd: list[str], **kwargs: Any) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False, **kwargs)


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    data = tmp_path_factory.mktemp("compat") / "data"
    live = LiveServer(data, scheduler="false", promote_after_s="0", auth="on").start()
    yield live
    live.stop()


@pytest.fixture(scope="module")
def depot(server: LiveServer) -> AuthedDepot:
    return AuthedDepot(server)


@pytest.fixture(scope="module")
def reader(depot: AuthedDepot) -> dict[str, str]:
    """A read token's header: what anyone allowed to look at runs has."""
    return depot.bearer(depot.token("read").token)


@pytest.fixture(scope="module")
def robots(server: LiveServer, depot: AuthedDepot, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Robot]:
    """Every SDK streams a run and uploads another, all at once, each with its robot's ingest token."""
    work = tmp_path_factory.mktemp("robots")

    def drive(version: str) -> Robot:
        robot = Robot(version, work / f"live-{version}.rrd", work / f"upload-{version}.rrd")
        robot.token = depot.token("ingest", robot=robot.robot_id).token
        env = {**ROBOT_ENV, "FLEET_ROBOT": robot.robot_id, "FLEET_TOKEN": robot.token}
        python = sdk_python(version)
        streamed = _run([python, ROBOT, "stream", server.grpc_url, str(robot.live_copy), robot.live_run], env=env)
        saved = _run([python, ROBOT, "save", str(robot.upload_copy), robot.upload_run], env=env)
        if streamed.returncode != 0 or saved.returncode != 0:
            robot.error = f"the robot failed: {streamed.stderr[-2000:]}{saved.stderr[-2000:]}"
            return robot
        answer = httpx.post(
            f"{server.url}/v1/uploads",
            content=robot.upload_copy.read_bytes(),
            headers=depot.bearer(robot.token),
            timeout=120,
        )
        robot.upload_answer = answer.json()
        if answer.status_code != 200:
            robot.error = f"upload refused: {answer.text}"
        return robot

    with ThreadPoolExecutor(max_workers=len(VERSIONS)) as pool:
        done = dict(zip(VERSIONS, pool.map(drive, VERSIONS), strict=True))
    # A stream's run closes when its stream ends: wait until the catalog says so. (Not yet listed is
    # not closed: the SDK can exit before the depot has catalogued its run.)
    server.wait_for(
        lambda: all(_run_json(server, r.live_run).get("status") == "closed" for r in done.values() if r.error is None),
        what="every live run closed",
    )
    return done


def _run_json(server: LiveServer, run_id: str) -> dict[str, Any]:
    """The run as GET /v1/runs/RUN shows it to an admin ({} if there is none)."""
    answer = httpx.get(f"{server.url}/v1/runs/{run_id}", headers=server.headers, timeout=10)
    return answer.json() if answer.status_code == 200 else {}  # type: ignore[no-any-return]


@dataclass
class Served:
    """A served recording and what the newest CLI says of it."""

    path: Path
    verify: subprocess.CompletedProcess[str]
    compare: subprocess.CompletedProcess[str]


def _serve_and_check(
    server: LiveServer,
    robots: dict[str, Robot],
    rerun_bin: str,
    out: Path,
    reader: dict[str, str],
) -> dict[tuple[str, str], Served]:
    jobs = [
        (r, run_id, copy)
        for r in robots.values()
        if r.error is None
        for run_id, copy in ((r.live_run, r.live_copy), (r.upload_run, r.upload_copy))
    ]

    def check(job: tuple[Robot, str, Path]) -> tuple[tuple[str, str], Served]:
        robot, run_id, copy = job
        path = out / f"{run_id}.rrd"
        with (
            httpx.stream("GET", f"{server.url}/v1/runs/{run_id}/recording.rrd", headers=reader, timeout=120) as answer,
            open(path, "wb") as fh,
        ):
            if answer.status_code != 200:
                fh.write(answer.read())  # not an .rrd: verify says so
            else:
                for piece in answer.iter_bytes():
                    fh.write(piece)
        verify = _run([rerun_bin, "rrd", "verify", "--check-footers", "true", str(path)])
        expected = stripped_copy(copy, out / f"{run_id}.expected.rrd")  # the depot strips the fleet token
        compare = _run([rerun_bin, "rrd", "compare", "--unordered", str(expected), str(path)])
        return (robot.version, run_id.split("-")[0]), Served(path, verify, compare)

    with ThreadPoolExecutor(max_workers=4) as pool:
        return dict(pool.map(check, jobs))


@pytest.fixture(scope="module")
def hot(
    server: LiveServer,
    robots: dict[str, Robot],
    rerun_bin: str,
    reader: dict[str, str],
    tmp_path_factory: pytest.TempPathFactory,
) -> dict[tuple[str, str], Served]:
    return _serve_and_check(server, robots, rerun_bin, tmp_path_factory.mktemp("hot"), reader)


@pytest.fixture(scope="module")
def sealed(
    server: LiveServer,
    robots: dict[str, Robot],
    hot: dict[tuple[str, str], Served],
    rerun_bin: str,
    reader: dict[str, str],
    tmp_path_factory: pytest.TempPathFactory,
) -> dict[tuple[str, str], Served]:
    """After every run was promoted to the warm tier (sealed: one file with a footer)."""
    answer = httpx.post(
        f"{server.url}/v1/retention/run", params={"action": "promote"}, headers=server.headers, timeout=600
    )
    assert answer.status_code == 200, answer.text
    for robot in robots.values():
        for run_id in (robot.live_run, robot.upload_run):
            assert robot.error is not None or _run_json(server, run_id)["tier"] == "warm", answer.text
    return _serve_and_check(server, robots, rerun_bin, tmp_path_factory.mktemp("sealed"), reader)


@pytest.mark.parametrize("version", VERSIONS)
def test_every_sdk_streams_and_uploads(version: str, server: LiveServer, robots: dict[str, Robot]):
    robot = robots[version]
    assert robot.error is None, robot.error
    assert robot.upload_answer["runs"] == [robot.upload_run]
    assert robot.upload_answer["chunks_new"] > 0
    for run_id in (robot.live_run, robot.upload_run):
        run = _run_json(server, run_id)
        assert run["application_id"] == "fleet_compat", run
        assert run["sdk_version"] == version and run["status"] == "closed"
        assert {e["path"] for e in run["entities"]} >= {"/world/robot", "/world/robot/lidar", "/robot/battery"}
        assert run["robot_id"] == robot.robot_id, run


@pytest.mark.parametrize("tier", ["hot", "sealed"])
@pytest.mark.parametrize("path", ["live", "upload"])
@pytest.mark.parametrize("version", VERSIONS)
def test_the_robot_token_is_never_served(
    version: str, path: str, tier: str, server: LiveServer, reader: dict[str, str], request: pytest.FixtureRequest
):
    """The token a robot sent in its fleet property is in neither the download's bytes (compressed
    or not) nor the run's properties; the rest of the property is kept."""
    robot: Robot = request.getfixturevalue("robots")[version]
    assert robot.error is None, robot.error
    assert places_holding([robot.live_copy], [robot.token], open_catalogs=False)  # the robot did log it
    served: Served = request.getfixturevalue(tier)[(version, path)]
    assert places_holding([served.path], [robot.token], open_catalogs=False) == []
    run_id = robot.live_run if path == "live" else robot.upload_run
    answer = httpx.get(f"{server.url}/v1/runs/{run_id}", headers=reader, timeout=10)
    assert answer.status_code == 200 and robot.token not in answer.text
    assert robot.token.rsplit(".", 1)[1] not in answer.text  # not even its signature
    assert answer.json()["properties"]["fleet"] == {"robot_id": robot.robot_id}


@pytest.mark.parametrize("tier", ["hot", "sealed"])
@pytest.mark.parametrize("path", ["live", "upload"])
@pytest.mark.parametrize("version", VERSIONS)
def test_served_file_equals_the_robot_copy_and_verifies(
    version: str, path: str, tier: str, request: pytest.FixtureRequest
):
    robot: Robot = request.getfixturevalue("robots")[version]
    assert robot.error is None, robot.error
    served: Served = request.getfixturevalue(tier)[(version, path)]
    assert served.verify.returncode == 0, served.verify.stdout + served.verify.stderr[-3000:]
    assert served.compare.returncode == 0, served.compare.stdout[-3000:] + served.compare.stderr[-3000:]


# --- rerun-sdk 0.22: told to upgrade ------------------------------------------------------------


LEGACY_STREAM = """
import sys
import rerun as rr
rr.init("fleet_compat", recording_id="legacy-0.22")
rr.connect_grpc(sys.argv[1])
rr.log("/robot/battery", rr.Points3D([[0.0, 0.0, 0.0]]))
rr.disconnect()
"""
LEGACY_SAVE = """
import sys
import rerun as rr
rr.init("fleet_compat", recording_id="legacy-0.22")
rr.save(sys.argv[1])
rr.log("/robot/battery", rr.Points3D([[0.0, 0.0, 0.0]]))
rr.disconnect()
"""


def test_sdk_0_22_upload_is_told_to_upgrade(server: LiveServer, tmp_path: Path):
    copy = tmp_path / "legacy.rrd"
    saved = _run([str(sdk_bin(LEGACY, "python")), "-c", LEGACY_SAVE, str(copy)])
    assert saved.returncode == 0, saved.stderr
    writer = AuthedDepot(server).token("write").token
    answer = httpx.post(
        f"{server.url}/v1/uploads", content=copy.read_bytes(), headers=AuthedDepot.bearer(writer), timeout=60
    )
    assert answer.status_code == 400, answer.text
    assert answer.json()["code"] == "UNSUPPORTED_RRD_VERSION"
    message = answer.json()["message"]
    assert "rerun-sdk 0.22.1" in message and "oldest supported rerun-sdk is 0.23" in message
    assert "pip install -U rerun-sdk" in message
    assert _run_json(server, "legacy-0.22") == {}


@pytest.mark.parametrize("scheme", ["rerun+http", "http"])
def test_sdk_0_22_stream_is_told_to_upgrade(server: LiveServer, scheme: str):
    """0.22's SDK calls rerun.sdk_comms.v0.MessageProxy/WriteMessages; the depot answers with the
    refusal, which the SDK prints. With a `rerun+http://` URL 0.22 sends the HTTP/2 pseudo-header
    `:scheme: rerun+http`, which gRPC's transport alone would refuse before any handler ran (the
    robot then saw only "Error parsing ':scheme' metadata"): the gRPC port's front makes it `http`."""
    url = f"{scheme}://127.0.0.1:{server.grpc_port}/proxy"
    streamed = _run([str(sdk_bin(LEGACY, "python")), "-c", LEGACY_STREAM, url])
    assert LEGACY_REFUSAL in streamed.stderr, streamed.stderr
    assert "FailedPrecondition" in streamed.stderr
    assert "Error parsing" not in streamed.stderr
    assert _run_json(server, "legacy-0.22") == {}
