"""Exports as people run them: from the command line into a folder (each episode downloaded as
exactly the snapshot's chunks), and as the depot's job into a place it may write, with progress in
the catalog, resumed by another pass after its process died, cancelled, refused when strict and
flagged. Auth on."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest
import rerun as rr

from catalog import dataset_exports as jobs
from catalog.db import session_scope
from catalog.models import DatasetExport
from services.cli.dataset_exports import export_here
from services.datasets import exports
from services.datasets.episodes import export_version
from services.datasets.export import ExportSpec, QualityError
from services.datasets.lerobot import layout
from services.datasets.local import open_rrd_file
from services.datasets.quality import Limits
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.datasets.conftest import ROBOT, writer
from tests.services.datasets.test_export import FRAMES, SPEC, grey, joints, snapshot, sources

S = 1_000_000_000


@pytest.fixture
def exporting(tmp_path: Path, fresh_catalog_url: str):  # type: ignore[no-untyped-def]
    place = tmp_path / "exports"
    place.mkdir()
    with open_depot(tmp_path / "depot", fresh_catalog_url, export_urls=[place.as_uri()]) as opened:
        yield opened, place


def places(depot: Depot) -> exports.Places:
    return exports.Places.of(depot.app.state.node.settings)


def test_the_episode_route_serves_exactly_the_snapshot_s_chunks(depot: Depot, tmp_path: Path):
    snapshot(depot, tmp_path, ["run-a"])
    version = writer(depot).dataset_version("drives", 1, chunk_ids=True)
    listed = set(version["episodes_page"][0]["chunk_ids"])
    out = tmp_path / "episode.rrd"
    writer(depot).download_episode("drives", 1, 0, out)
    recording = open_rrd_file(out)
    try:
        held = {r.chunk_id.hex() for r in recording.index() if r.chunk_id is not None}
    finally:
        recording.close()
    assert held == listed
    missing = depot.client.get("/v1/datasets/drives/1/episodes/7/recording.rrd", headers=bearer(depot.token("read")))
    assert missing.status_code == 404 and "no episode 7" in missing.json()["message"]


def test_the_command_line_export_equals_the_depot_s(depot: Depot, tmp_path: Path):
    snapshot(depot, tmp_path, ["run-a", "run-b"])
    here = export_here(writer(depot), "drives", 1, SPEC, tmp_path / "here", Limits(), strict=False)
    export_version(sources(depot), "drives", 1, SPEC, tmp_path / "there")
    assert here.info is not None and here.info["total_frames"] == 2 * FRAMES
    assert [r.exported_as for r in here.reports] == [0, 1]
    for name in (layout.INFO_PATH, layout.STATS_PATH, layout.data_path(0), layout.data_path(1)):
        assert (tmp_path / "here" / name).read_bytes() == (tmp_path / "there" / name).read_bytes(), name


def frozen_drive(path: Path, run_id: str, frozen_from: int) -> bytes:
    """A drive whose camera shows one image from frame `frozen_from` on, and whose /joints skips a frame."""
    rec = rr.RecordingStream("export_test", recording_id=run_id)
    rec.save(str(path))
    rec.send_property("fleet", rr.AnyValues(robot_id=ROBOT))
    start = 1_790_000_000 * S
    for i in range(FRAMES):
        rec.set_time("sim_time", timestamp=np.datetime64(start + i * S // 10, "ns"))
        rec.log("/joints", rr.Scalars(joints(i)))
        rec.log("/cmd", rr.Scalars([v + 0.25 for v in joints(i)]))
        shade = grey(min(i, frozen_from))
        rec.log("/camera/front", rr.Image(np.full((24, 32, 3), shade, dtype=np.uint8)))
    rec.flush()
    rec.disconnect()
    return path.read_bytes()


def test_quality_flags_are_reported_and_refuse_a_strict_export(depot: Depot, tmp_path: Path):
    data = frozen_drive(tmp_path / "frozen.rrd", "run-frozen", frozen_from=5)  # 2.5 s of one image
    answer = depot.client.post("/v1/uploads", content=data, headers=bearer(depot.token("ingest", robot=ROBOT)))
    assert answer.status_code == 200, answer.text
    writer(depot).create_dataset("drives", robot=[ROBOT], timeline="sim_time", fps=10)
    missing = ExportSpec(("/joints", "/gripper"), ("/cmd",), SPEC.cameras, "t", 10)
    checked = export_version(sources(depot), "drives", 1, missing, None)
    (report,) = checked.reports
    assert {(f.check, f.entity) for f in report.flags} == {("missing_entity", "/gripper"), ("hot_run", None)}
    assert report.exported_as is None  # a missing entity: nothing fills its vector, nothing more is read
    result = export_version(sources(depot), "drives", 1, SPEC, tmp_path / "out")
    (report,) = result.reports
    assert report.exported_as == 0 and {f.check for f in report.flags} == {"frozen_camera", "hot_run"}
    frozen = next(f for f in report.flags if f.check == "frozen_camera")
    assert frozen.entity == "/camera/front" and "2.4 s" in frozen.detail
    with pytest.raises(QualityError, match="frozen_camera /camera/front"):
        export_here(writer(depot), "drives", 1, SPEC, tmp_path / "strict", Limits(), strict=True)
    assert not (tmp_path / "strict" / layout.INFO_PATH).exists()
    quiet = export_version(sources(depot), "drives", 1, SPEC, tmp_path / "quiet", limits=Limits(frozen_s=5.0))
    assert {f.check for f in quiet.reports[0].flags} == {"hot_run"}


def test_a_depot_export_job_writes_the_target_with_progress(exporting: tuple[Depot, Path], tmp_path: Path):
    depot, place = exporting
    snapshot(depot, tmp_path, ["run-a", "run-b"])
    target = (place / "drives-1").as_uri()
    job = writer(depot).export_dataset(
        "drives@1",
        target,
        observation=["/joints"],
        action=["/cmd"],
        cameras={"/camera/front": "observation.images.front"},
        task="pick the box",
    )
    assert job["state"] == "queued" and job["episodes"] == 2 and job["spec"]["fps"] == 10
    assert exports.run_due(sources(depot), places(depot), "test-node") == job["id"]
    done = writer(depot).export(job["id"])
    assert (done["state"], done["done"], done["frames"]) == ("done", 2, 2 * FRAMES), done
    assert done["bytes"] == sum(p.stat().st_size for p in (place / "drives-1").rglob("*") if p.is_file())
    info = json.loads((place / "drives-1" / layout.INFO_PATH).read_text())
    assert info["total_frames"] == 2 * FRAMES
    state = pq.read_table(place / "drives-1" / layout.data_path(1)).column("observation.state").to_pylist()
    assert np.allclose(state, [joints(i) for i in range(FRAMES)])
    assert not (place / "drives-1" / ".export").exists()  # progress records stay in the depot's staging
    assert not (depot.app.state.node.settings.data_dir / "exports" / job["id"]).exists()
    assert [j["id"] for j in writer(depot).exports("drives@1")] == [job["id"]]


def test_a_job_left_by_a_dead_process_is_resumed(exporting: tuple[Depot, Path], tmp_path: Path):
    depot, place = exporting
    snapshot(depot, tmp_path, ["run-a", "run-b"])
    job = writer(depot).export_dataset("drives@1", (place / "out").as_uri(), observation=["/joints"])
    src = sources(depot)
    staging = places(depot).staging / job["id"]
    export_version(src, "drives", 1, ExportSpec(("/joints",), (), (), "", 10), staging)  # as far as a dead run got
    long_ago = dt.datetime.now(dt.UTC) - dt.timedelta(minutes=5)
    with session_scope(src.catalog, write=True) as session:
        assert jobs.claim(session, job["id"], "dead-node", long_ago, long_ago + dt.timedelta(hours=1))
        session.get(DatasetExport, job["id"]).heartbeat_at = long_ago  # type: ignore[union-attr]
    assert exports.run_due(src, places(depot), "live-node") == job["id"]
    assert writer(depot).export(job["id"])["state"] == "done"
    assert json.loads((place / "out" / layout.INFO_PATH).read_text())["total_episodes"] == 2


def test_a_job_is_cancelled_and_a_strict_one_fails_naming_its_flags(exporting: tuple[Depot, Path], tmp_path: Path):
    depot, place = exporting
    snapshot(depot, tmp_path, ["run-a"])
    queued = writer(depot).export_dataset("drives@1", (place / "a").as_uri(), observation=["/joints"])
    assert writer(depot).cancel_export(queued["id"])["state"] == "cancelled"
    again = depot.client.delete(f"/v1/exports/{queued['id']}", headers=bearer(depot.token("write")))
    assert again.status_code == 409 and "cancelled" in again.json()["message"]
    strict = writer(depot).export_dataset("drives@1", (place / "b").as_uri(), observation=["/joints"], strict=True)
    assert exports.run_due(sources(depot), places(depot), "node") == strict["id"]
    failed = writer(depot).export(strict["id"])
    assert failed["state"] == "failed" and "hot_run" in failed["error"] and "--strict" in failed["error"]
    assert not (place / "b").exists()


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"dataset": "drives", "to": "file:///x"}, "NAME@N"),
        ({"dataset": "drives@1", "to": "file:///elsewhere"}, "not under a place"),
        ({"dataset": "drives@1", "to": "http://x/y"}, "file:///PATH or s3://"),
        ({"dataset": "drives@1", "to": "PLACE/../up"}, "file:///PATH or s3://"),
        ({"dataset": "drives@1", "to": "PLACE", "format": "hdf5"}, "one of lerobot"),
        ({"dataset": "drives@1", "to": "PLACE", "video_codec": "vp9"}, "h264"),
        ({"dataset": "drives@1", "to": "PLACE", "cameras": {"/c": "front"}}, "observation.images.NAME"),
        ({"dataset": "drives@1", "to": "PLACE", "observation": []}, "name what to export"),
        ({"dataset": "drives@9", "to": "PLACE", "observation": ["/joints"]}, "no dataset version drives@9"),
    ],
)
def test_a_bad_export_is_one_clear_refusal(
    exporting: tuple[Depot, Path], tmp_path: Path, body: dict[str, Any], field: str
) -> None:
    depot, place = exporting
    snapshot(depot, tmp_path, ["run-a"])
    sent = {"observation": ["/joints"], **body}
    sent["to"] = sent["to"].replace("PLACE", place.as_uri())
    answer = depot.client.post("/v1/exports", json=sent, headers=bearer(depot.token("write")))
    assert answer.status_code in (404, 422), answer.text
    assert field in answer.text


def test_a_depot_without_export_places_says_how_to_export(depot: Depot, tmp_path: Path):
    snapshot(depot, tmp_path, ["run-a"])
    body = {"dataset": "drives@1", "to": "s3://bucket/x", "observation": ["/joints"]}
    answer = depot.client.post("/v1/exports", json=body, headers=bearer(depot.token("write")))
    assert answer.status_code == 422 and "FLEET_EXPORT_URLS" in answer.json()["message"]
    reader = depot.client.post("/v1/exports", json=body, headers=bearer(depot.token("read")))
    assert reader.status_code == 403


def test_a_depot_export_job_puts_the_dataset_into_s3(depot: Depot, tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """An S3 target (moto): every file under the prefix, meta/ included, as the folder export holds it."""
    for name, value in (("AWS_ACCESS_KEY_ID", "testing"), ("AWS_SECRET_ACCESS_KEY", "testing")):
        monkeypatch.setenv(name, value)
    from moto import mock_aws

    snapshot(depot, tmp_path, ["run-a"])
    with mock_aws():
        import boto3

        s3 = boto3.client("s3", region_name="us-east-1")
        s3.create_bucket(Bucket="datasets")
        allowed = exports.Places(("s3://datasets/team",), tmp_path / "staging", region="us-east-1")
        request = exports.ExportRequest("drives", 1, "lerobot", "s3://datasets/team/drives-1", SPEC, Limits(), False)
        job = exports.create(sources(depot), allowed, request, "alice")
        assert exports.run_due(sources(depot), allowed, "node") == job["id"]
        assert writer(depot).export(job["id"])["state"] == "done"
        keys = {o["Key"] for o in s3.list_objects_v2(Bucket="datasets", Prefix="team/drives-1/")["Contents"]}
        export_version(sources(depot), "drives", 1, SPEC, tmp_path / "folder")
        held = {
            "team/drives-1/" + p.relative_to(tmp_path / "folder").as_posix()
            for p in (tmp_path / "folder").rglob("*")
            if p.is_file() and ".export" not in p.parts
        }
        assert keys == held and "team/drives-1/meta/info.json" in keys
        info = s3.get_object(Bucket="datasets", Key="team/drives-1/meta/info.json")["Body"].read()
        assert json.loads(info)["total_frames"] == FRAMES
