"""An S3 outage does not stop ingest: with the real SeaweedFS server stopped, uploads are taken and
stay hot, promotion fails and backs off; once the server is back, promotion catches up."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.seaweedfs import SeaweedFS
from tests.services.ingest.live_server import LiveServer
from tests.services.rrd.recordings import Recording, rerun_rrd_ok

pytestmark = [pytest.mark.s3server, pytest.mark.slow, pytest.mark.sdk]

BUCKET = "fleet-outage"
SCENES = ("transforms", "points", "scalars", "textlogs")
CATCH_UP_S = 60  # promotion backs off 1, 2, 4 ... s per run: a short outage is caught up in seconds


@pytest.fixture
def weed(tmp_path: Path) -> Iterator[SeaweedFS]:
    server = SeaweedFS(tmp_path / "weed")
    server.start()
    try:
        yield server
    finally:
        server.stop()


def get(server: LiveServer, path: str) -> Any:
    answer = httpx.get(f"{server.url}{path}", timeout=30)
    assert answer.status_code == 200, f"{path}: {answer.status_code} {answer.text}"
    return answer.json()


def tier(server: LiveServer, run_id: str) -> str:
    found: str = get(server, f"/v1/runs/{run_id}")["tier"]
    return found


def upload(server: LiveServer, rec: Recording) -> str:
    answer = httpx.post(f"{server.url}/v1/uploads", content=rec.data, timeout=60)
    assert answer.status_code == 200, answer.text
    run_id: str = rec.recordings[0]["recording_id"]
    assert answer.json()["runs"] == [run_id]
    return run_id


def failed_promotions(server: LiveServer, run_id: str) -> list[dict[str, Any]]:
    return [
        j
        for j in get(server, "/v1/retention")["recent_jobs"]
        if j["job"] == "promote" and j["outcome"] == "failed" and f"promote {run_id}:" in j["detail"]
    ]


def test_ingest_goes_on_through_an_s3_outage_and_promotion_catches_up(
    weed: SeaweedFS, tmp_path: Path, recordings: dict[str, Recording], rerun_bin: str, monkeypatch: pytest.MonkeyPatch
):
    weed.client().create_bucket(Bucket=BUCKET)
    for name, value in (
        ("AWS_ACCESS_KEY_ID", "test"),
        ("AWS_SECRET_ACCESS_KEY", "test"),
        ("AWS_DEFAULT_REGION", "us-east-1"),
    ):
        monkeypatch.setenv(name, value)
    server = LiveServer(
        tmp_path / "data",
        warm_url=f"s3://{BUCKET}/warm",
        cold_url=f"s3://{BUCKET}/cold",
        s3_endpoint_url=weed.endpoint,
        promote_after_s="0",
        promote_interval_s="0.5",
    )
    try:
        server.start()
        before = upload(server, recordings["transforms"])  # the set-up works: promoted while S3 is up
        server.wait_for(lambda: tier(server, before) == "warm", timeout=30, what="promotion before the outage")

        weed.stop()
        outage = [upload(server, recordings[s]) for s in ("points", "scalars")]  # ingest does not wait for S3
        server.wait_for(
            lambda: all(failed_promotions(server, r) for r in outage),
            timeout=30,
            what="promotion to fail during the outage",
        )
        late = upload(server, recordings["textlogs"])  # still taken after promotion failed
        runs = [*outage, late]
        assert {r["id"] for r in get(server, "/v1/runs?tier=hot")["runs"]} == set(runs)
        assert tier(server, before) == "warm"
        unreachable = httpx.get(f"{server.url}/v1/runs/{before}/recording.rrd", timeout=60)  # a warm run: in S3
        assert unreachable.status_code == 503 and unreachable.json()["code"] == "UNAVAILABLE", unreachable.text
        (failure, *_) = failed_promotions(server, outage[0])
        assert "StorageError" in failure["detail"] and "0 done" in failure["detail"]

        weed.start()
        back = time.monotonic()
        server.wait_for(
            lambda: all(tier(server, r) == "warm" for r in runs),
            timeout=CATCH_UP_S,
            what=f"promotion to catch up within {CATCH_UP_S}s of S3 returning",
        )
        caught_up = time.monotonic() - back
        print(f"promotion caught up {caught_up:.1f}s after S3 returned")

        for run_id in runs:
            shown = get(server, f"/v1/runs/{run_id}")
            assert [e["action"] for e in shown["events"]] == ["promote"]  # sealed once, as a whole
            assert {o["name"] for o in shown["objects"]} >= {"recording.rrd", "chunks.parquet"}
            for obj in shown["objects"]:  # what the catalog says is in the bucket is there, whole
                held = weed.client().head_object(Bucket=BUCKET, Key=f"warm/{obj['key']}")
                assert held["ContentLength"] == obj["size"], obj
        served = {}
        for run_id in [before, *runs]:
            out = tmp_path / f"{run_id}.rrd"
            answer = httpx.get(f"{server.url}/v1/runs/{run_id}/recording.rrd", timeout=60)
            assert answer.status_code == 200, answer.text
            out.write_bytes(answer.content)
            served[run_id] = out
        assert not list((tmp_path / "data" / "hot").glob("*/run.rrd")), "hot copies left after promotion"
    finally:
        server.stop()
    sources = {recordings[s].recordings[0]["recording_id"]: recordings[s].path for s in SCENES}
    for run_id, out in served.items():
        rerun_rrd_ok(rerun_bin, "verify", out)
        rerun_rrd_ok(rerun_bin, "compare", "--unordered", sources[run_id], out)
