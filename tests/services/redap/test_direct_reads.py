"""Direct reads from the bucket (FLEET_DIRECT_READS=presigned), end to end: a real `fleet serve`
(auth on) seals runs into a SeaweedFS bucket that serves signed requests only, and Rerun's own SDK
(`CatalogClient`, 0.41) reads them with the presigned URLs FindChunks hands out: the same rows as
Rerun's dataframe API reads from the robot's file, with the depot's FetchChunks serving nothing.

The URLs: one object each, ranged reads work, they expire, they hold no secret, and an unsigned or
tampered read of the bucket is refused (so it is the signature that lets the client in)."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
import time
import urllib.parse
from collections.abc import Iterator
from pathlib import Path

import httpx
import pyarrow as pa
import pytest

from services.redap.dataframe import read_dataframe_part
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from tests.seaweedfs import SIGNED_ONLY_ACCESS_KEY, SIGNED_ONLY_SECRET_KEY, seaweedfs
from tests.services.ingest.live_server import LiveServer
from tests.services.redap.client import Redap
from tests.services.redap.golden import EVERYTHING, time_range
from tests.services.redap.test_reader_e2e import _comparable

pytestmark = [pytest.mark.sdk, pytest.mark.s3server, pytest.mark.slow]

BUCKET = "fleet-direct"
DATASET = "fleet_direct"
RUN = "direct-robot-run"
FRAMES = 60
TTL_S = 120


def _log_robot(path: Path) -> Path:
    """A robot's file by the real SDK: a pose, a scalar and a log line per frame, chunks of five rows."""
    script = f"""
import rerun as rr
rec = rr.RecordingStream({DATASET!r}, recording_id={RUN!r})
rec.save({str(path)!r})
rec.send_property("fleet", rr.AnyValues(robot_id="robot-direct"))
rec.log("/world/map", rr.Points3D([[0.0, 0.0, 0.0], [2.0, 1.0, 0.0]]), static=True)
for i in range({FRAMES}):
    rec.set_time("frame", sequence=i)
    rec.log("/world/robot", rr.Transform3D(translation=[i * 0.1, 0.0, 0.0]))
    rec.log("/robot/battery", rr.Scalars(100.0 - i * 0.5))
    rec.log("/robot/log", rr.TextLog(f"step {{i}}"))
rec.flush()
"""
    env = {**os.environ, "RERUN_FLUSH_NUM_ROWS": "5", "RERUN_FLUSH_TICK_SECS": "1000"}
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120, env=env, capture_output=True)
    return path


@pytest.fixture(scope="module")
def robot_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _log_robot(tmp_path_factory.mktemp("robot") / f"{RUN}.rrd")


@pytest.fixture(scope="module")
def bucket(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A bucket that serves signed requests only; yields its S3 endpoint."""
    import boto3

    with seaweedfs(tmp_path_factory.mktemp("weed"), signed_only=True) as endpoint:
        boto3.client(
            "s3",
            endpoint_url=endpoint,
            region_name="us-east-1",
            aws_access_key_id=SIGNED_ONLY_ACCESS_KEY,
            aws_secret_access_key=SIGNED_ONLY_SECRET_KEY,
        ).create_bucket(Bucket=BUCKET)
        yield endpoint


@pytest.fixture(scope="module")
def depot(robot_file: Path, bucket: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LiveServer, str]]:
    """`fleet serve` with auth on and direct reads, the robot's run uploaded and sealed into the
    bucket; yields it and a read token."""
    saved = {k: os.environ.get(k) for k in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION")}
    os.environ.update(AWS_ACCESS_KEY_ID=SIGNED_ONLY_ACCESS_KEY, AWS_DEFAULT_REGION="us-east-1")
    os.environ["AWS_SECRET_ACCESS_KEY"] = SIGNED_ONLY_SECRET_KEY
    server = LiveServer(
        tmp_path_factory.mktemp("depot") / "data",
        auth="on",
        warm_url=f"s3://{BUCKET}/warm",
        cold_url=f"s3://{BUCKET}/cold",
        s3_endpoint_url=bucket,
        direct_reads="presigned",
        direct_url_ttl_s=str(TTL_S),
    )
    try:
        server.start()
        answer = httpx.post(
            f"{server.url}/v1/uploads", content=robot_file.read_bytes(), headers=server.headers, timeout=120
        )
        assert answer.status_code == 200, answer.text
        server.wait_for(functools.partial(_promoted, server), timeout=60, what="the run sealed")
        made = httpx.post(
            f"{server.url}/v1/tokens", json={"scopes": ["read"], "name": "analyst"}, headers=server.headers, timeout=30
        )
        assert made.status_code == 201, made.text
        yield server, made.json()["token"]
    finally:
        server.stop()
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _promoted(server: LiveServer) -> bool:
    answer = httpx.post(f"{server.url}/v1/runs/{RUN}/promote", headers=server.headers, timeout=60)
    return answer.status_code == 200 or (answer.status_code == 409 and "warm already" in answer.text)


def _served(server: LiveServer, how: str) -> float:
    for line in httpx.get(f"{server.url}/metrics", headers=server.headers, timeout=10).text.splitlines():
        if line.startswith(f'fleet_catalog_chunks_served_total{{how="{how}"}}'):
            return float(line.split()[-1])
    raise AssertionError(f"no fleet_catalog_chunks_served_total for {how}")


def test_the_sdk_reads_a_sealed_run_from_the_bucket_not_through_the_depot(
    depot: tuple[LiveServer, str], robot_file: Path
):
    import rerun as rr

    server, token = depot
    fetched_before, direct_before = _served(server, "depot"), _served(server, "direct")
    client = rr.catalog.CatalogClient(f"rerun+http://127.0.0.1:{server.grpc_port}", token=token)
    found = client.get_dataset(DATASET).reader(index="frame").to_arrow_table()
    expected = rr.chunk.RrdReader(robot_file).stream().collect().reader("frame").to_arrow_table()
    assert _comparable(found) == _comparable(expected)
    assert _served(server, "depot") == fetched_before, "the depot served chunks it should have left to the bucket"
    assert _served(server, "direct") > direct_before
    del client


def _candidate_rows(server: LiveServer, token: str, mode: cloud_pb2.DirectUrlMode) -> pa.Table:
    """FindChunks over every chunk of the dataset, as the SDK asks it, with `direct_url_mode`."""

    redap = Redap(server.grpc_port, token=token)
    try:
        entries = redap.call("FindEntries", cloud_pb2.FindEntriesRequest(filter=cloud_pb2.EntryFilter(name=DATASET)))
        entry = str(Tuid.from_proto(entries.entries[0].id.id))
        request = cloud_pb2.FindChunksRequest(contents=EVERYTHING, range=time_range("frame"), direct_url_mode=mode)
        parts = [read_dataframe_part(r.data, "data") for r in redap.call("FindChunks", request, entry=entry)]
        return pa.concat_tables(parts)
    finally:
        redap.close()


def test_presigned_urls_name_one_object_expire_and_hold_no_secret(depot: tuple[LiveServer, str], bucket: str):
    server, token = depot
    rows = _candidate_rows(server, token, cloud_pb2.DIRECT_URL_MODE_SIGNED)
    urls = set(rows.column("rerun_layer_direct_url").to_pylist())
    assert len(urls) == 1 and None not in urls, urls
    url = urls.pop()
    assert url.startswith(bucket) and f"/{BUCKET}/warm/" in url and url.split("?")[0].endswith("/recording.rrd")
    assert SIGNED_ONLY_SECRET_KEY not in url
    query = urllib.parse.parse_qs(urllib.parse.urlsplit(url).query)
    assert int(query["X-Amz-Expires"][0]) == TTL_S
    expires = set(rows.column("rerun_layer_direct_url_expires_at").to_pylist())
    assert len(expires) == 1
    assert 0 < expires.pop() - time.time_ns() <= TTL_S * 10**9

    ranged = httpx.get(url, headers={"Range": "bytes=0-3"}, timeout=10)
    assert ranged.status_code == 206 and ranged.content == b"RRF2", ranged.text
    assert httpx.get(url.split("?")[0], headers={"Range": "bytes=0-3"}, timeout=10).status_code == 403
    elsewhere = url.replace("/recording.rrd?", "/chunks.parquet?")
    assert httpx.get(elsewhere, timeout=10).status_code == 403, "a URL must open its one object only"


def test_a_client_that_asks_for_no_urls_gets_none(depot: tuple[LiveServer, str]):
    server, token = depot
    rows = _candidate_rows(server, token, cloud_pb2.DIRECT_URL_MODE_OMIT)
    assert rows.num_rows > 0
    assert rows.column("rerun_layer_direct_url").null_count == rows.num_rows
