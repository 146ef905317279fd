"""MCAP uploads on a real `fleet serve` with auth on: converted by the pinned Rerun CLI and filed once,
listed as imports with their state, bad files refused with their reason and quarantined, a recording
written further adding only what is new, and a failed import retried."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.services.imports.mcaps import bomb, corrupt, json_mcap, truncated
from tests.services.ingest.authed import AuthedDepot
from tests.services.ingest.live_server import LiveServer

pytestmark = [pytest.mark.slow, pytest.mark.sdk]
RERUN = Path(__file__).resolve().parents[3] / ".venv" / "bin" / "rerun"


@pytest.fixture(scope="module")
def depot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[AuthedDepot]:
    live = LiveServer(tmp_path_factory.mktemp("mcap") / "data", auth="on", durability="off").start()
    try:
        yield AuthedDepot(live)
    finally:
        live.stop()


def upload(depot: AuthedDepot, path: Path, token: str | None = None, **params: str) -> httpx.Response:
    return httpx.post(
        f"{depot.live.url}/v1/uploads",
        content=path.read_bytes(),
        params={"name": path.name, **params},
        headers=depot.bearer(token or depot.admin),
        timeout=120,
    )


def imported(depot: AuthedDepot, import_id: str) -> dict[str, Any]:
    answer = depot.get(f"/v1/imports/{import_id}")
    assert answer.status_code == 200, answer.text
    found: dict[str, Any] = answer.json()
    return found


def download(depot: AuthedDepot, run_id: str, target: Path) -> Path:
    answer = depot.get(f"/v1/runs/{run_id}/recording.rrd")
    assert answer.status_code == 200, answer.text
    target.write_bytes(answer.content)
    return target


def values_in(rrd: Path) -> str:
    """`rerun rrd print` of a recording, verbose enough to show the messages' entities."""
    done = subprocess.run([str(RERUN), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_a_bag_is_converted_filed_once_and_verified(depot: AuthedDepot, tmp_path: Path) -> None:
    bag = json_mcap(tmp_path / "drive.mcap", 500, topics=("/sensors/temp", "/sensors/speed"))
    first = upload(depot, bag, run_id="mcap-drive-1", application="bench-bags")
    assert first.status_code == 200, first.text
    report = first.json()
    assert report["runs"] == ["mcap-drive-1"] and report["chunks_new"] > 0 and report["already_held"] is False
    row = imported(depot, report["import"]["id"])
    assert (row["state"], row["kind"], row["runs"], row["name"]) == ("filed", "mcap", ["mcap-drive-1"], "drive.mcap")
    assert row["converter"].startswith("rerun-cli 0.") and len(row["digest"]) == 64

    again = upload(depot, bag, run_id="mcap-drive-1")
    assert again.status_code == 200, again.text
    assert again.json()["already_held"] is True and again.json()["chunks_new"] == 0
    assert imported(depot, again.json()["import"]["id"])["held_by"] == report["import"]["id"]
    run = depot.run("mcap-drive-1")
    assert run is not None and run["chunks"] == report["chunks_new"] and run["application_id"] == "bench-bags"

    served = download(depot, "mcap-drive-1", tmp_path / "served.rrd")
    verify = subprocess.run([str(RERUN), "rrd", "verify", str(served)], capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr
    printed = values_in(served)
    assert "/sensors/temp" in printed and "/sensors/speed" in printed


def test_an_ingest_token_files_the_bag_under_its_robot(depot: AuthedDepot, tmp_path: Path) -> None:
    robot = depot.token("ingest", robot="rover-3")
    bag = json_mcap(tmp_path / "r.mcap", 50, metadata={"foxglove": {"deviceName": "someone-else"}})
    answer = upload(depot, bag, robot.token)
    assert answer.status_code == 200, answer.text
    (run_id,) = answer.json()["runs"]
    assert run_id.startswith("mcap-")  # no run named: one derived from the file's digest
    run = depot.run(run_id)
    assert run is not None and run["robot_id"] == "rover-3"
    refused = upload(depot, bag, robot.token, robot="rover-4")
    assert refused.status_code == 403 and "rover-3" in refused.json()["message"]
    named = json_mcap(tmp_path / "n.mcap", 20, metadata={"foxglove": {"deviceName": "dock-9"}})
    answer = upload(depot, named)  # an admin's token names no robot: the file's metadata does
    assert answer.status_code == 200, answer.text
    run = depot.run(answer.json()["runs"][0])
    assert run is not None and run["robot_id"] == "dock-9"


@pytest.mark.parametrize(
    ("make", "code", "why"),
    [
        (truncated, "INVALID_MCAP", "truncated"),
        (corrupt, "INVALID_MCAP", "is corrupt"),
    ],
)
def test_a_bad_bag_is_refused_with_its_reason_listed_and_quarantined(
    depot: AuthedDepot,
    tmp_path: Path,
    make: Any,
    code: str,
    why: str,
) -> None:
    bad = make(json_mcap(tmp_path / "good.mcap", 3000), tmp_path / "bad.mcap")
    answer = upload(depot, bad)
    assert answer.status_code == 400, answer.text
    assert answer.json()["code"] == code and why in answer.json()["message"], answer.text
    row = imported(depot, answer.json()["import"]["id"])
    assert row["state"] == "failed" and why in row["reason"] and row["quarantined"] is True
    listed = depot.get("/v1/imports", state="failed", kind="mcap").json()["imports"]
    assert row["id"] in [i["id"] for i in listed]
    original = depot.get(f"/v1/imports/{row['id']}/original")
    assert original.status_code == 200 and original.content == bad.read_bytes()
    reader = depot.token("read")
    assert depot.get(f"/v1/imports/{row['id']}/original", reader.token).status_code == 403
    assert depot.get(f"/v1/imports/{row['id']}", reader.token).status_code == 200
    assert depot.live.healthy()


def test_a_recording_written_further_adds_only_its_new_messages(depot: AuthedDepot, tmp_path: Path) -> None:
    short = json_mcap(tmp_path / "grow-1.mcap", 200, chunk_size=1)  # a chunk per message, 100 bytes each
    longer = json_mcap(tmp_path / "grow-2.mcap", 500, chunk_size=1)
    first = upload(depot, short, run_id="mcap-growing")
    assert first.status_code == 200, first.text
    second = upload(depot, longer)
    assert second.status_code == 200, second.text
    assert (
        second.json()["runs"] == ["mcap-growing"] and second.json()["import"]["extends"] == first.json()["import"]["id"]
    )

    copy = upload(depot, json_mcap(tmp_path / "copy.mcap", 500, chunk_size=1))  # grow-2's bytes again
    assert copy.status_code == 200 and copy.json()["already_held"] and copy.json()["runs"] == ["mcap-growing"]

    served = values_in(download(depot, "mcap-growing", tmp_path / "growing.rrd"))
    assert served.count("/sensors/temp") >= 2  # both parts' messages are in the run

    earlier = upload(depot, json_mcap(tmp_path / "grow-0.mcap", 100, chunk_size=1))
    assert earlier.status_code == 409 and "earlier copy" in earlier.json()["message"], earlier.text


def test_a_failed_conversion_is_retried_and_a_bomb_is_stopped(tmp_path: Path) -> None:
    live = LiveServer(tmp_path / "data", auth="on", durability="off", mcap_timeout_s="0.01").start()
    try:
        depot = AuthedDepot(live)
        bag = json_mcap(tmp_path / "slow.mcap", 200)
        answer = upload(depot, bag, run_id="mcap-retried")
        assert answer.status_code == 413 and "FLEET_MCAP_TIMEOUT_S" in answer.json()["message"], answer.text
        import_id = answer.json()["import"]["id"]
        assert imported(depot, import_id)["quarantined"] is True
        writer = depot.token("write")
        reader = depot.token("read")
        assert (
            httpx.post(f"{live.url}/v1/imports/{import_id}/retry", headers=depot.bearer(reader.token)).status_code
            == 403
        )
    finally:
        live.stop()
    live = LiveServer(tmp_path / "data", auth="on", durability="off", mcap_memory_mb="256")
    live.http_port, live.grpc_port = live.http_port, live.grpc_port
    live.start()
    try:
        depot = AuthedDepot(live)
        retried = httpx.post(
            f"{live.url}/v1/imports/{import_id}/retry", headers=depot.bearer(writer.token), timeout=120
        )
        assert retried.status_code == 200, retried.text
        assert retried.json()["runs"] == ["mcap-retried"] and retried.json()["chunks_new"] > 0
        row = imported(depot, import_id)
        assert row["state"] == "filed" and row["reason"] is None
        assert upload(depot, bag).json()["already_held"] is True  # the retried file is held now

        blown = upload(depot, bomb(tmp_path / "bomb.mcap", 400 << 20))
        assert blown.status_code == 413 and "FLEET_MCAP_MEMORY_MB" in blown.json()["message"], blown.text
        assert blown.json()["import"]["id"] and live.healthy()
    finally:
        live.stop()
