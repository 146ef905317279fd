"""`POST /v1/uploads` and `fleet upload` against a real `fleet serve`."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import sqlalchemy as sa

from services.rrd import ArrowMessage, errors, iter_events
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    """One depot for the module: each test uploads recordings of its own, none kills it."""
    live = LiveServer(tmp_path_factory.mktemp("rest") / "data").start()
    yield live
    live.stop()


def _fleet_upload(server: LiveServer, *paths: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [FLEET, "upload", "--api-url", server.url, *map(str, paths)], capture_output=True, text=True, timeout=300
    )


def test_fleet_upload_then_again(server: LiveServer, recordings: dict[str, Recording]):
    rec = recordings["transforms"]
    chunks = sum(isinstance(e, ArrowMessage) for e in iter_events(rec.path))
    first = _fleet_upload(server, rec.path)
    assert first.returncode == 0, first.stderr
    assert f"{chunks} new chunks" in first.stdout and "0 already held" in first.stdout
    second = _fleet_upload(server, rec.path)
    assert "0 new chunks" in second.stdout and f"{chunks} already held" in second.stdout


def test_a_body_that_turns_bad_keeps_what_came_before(server: LiveServer, recordings: dict[str, Recording]):
    cut = recordings["cut"]
    good = []
    fault = None
    try:
        for event in iter_events(cut.path):
            if isinstance(event, ArrowMessage):
                good.append(event)
    except errors.TruncatedError as exc:
        fault = exc
    assert fault is not None
    response = httpx.post(f"{server.url}/v1/uploads", content=cut.data, timeout=60)
    assert response.status_code == 400
    body = response.json()
    assert body["code"] == "INVALID_RRD" and body["offset"] == fault.offset
    assert f"at byte {fault.offset}" in body["message"]
    assert body["accepted"]["chunks_new"] == len(good)
    result = _fleet_upload(server, cut.path)
    assert result.returncode == 1
    assert "truncated" in result.stderr and f"at byte {fault.offset}" in result.stderr


def test_not_an_rrd(server: LiveServer):
    response = httpx.post(f"{server.url}/v1/uploads", content=b'{"hello": "world"}', timeout=60)
    assert response.status_code == 400
    assert response.json()["offset"] == 0 and "not an RRD" in response.json()["message"]


def test_service_down_is_one_clear_line(tmp_path: Path, recordings: dict[str, Recording]):
    result = subprocess.run(
        [FLEET, "upload", "--api-url", "http://127.0.0.1:9", str(recordings["points"].path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "cannot reach the fleet service" in lines[0] and "FLEET_API_URL" in lines[0]


BIG_SCRIPT = """
import sys, numpy as np, rerun as rr
rec = rr.RecordingStream("fleet_big", recording_id="big-upload")
rec.save(sys.argv[1])
rng = np.random.default_rng(1)
for i in range(int(sys.argv[2])):
    rec.set_time("frame", sequence=i)
    rec.log("/camera", rr.Image(rng.integers(0, 255, (576, 1024, 3), dtype=np.uint8)))
rec.flush()
"""


def _peak_rss(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmHWM")


def test_large_upload_in_constant_memory(server: LiveServer, tmp_path: Path):
    big = tmp_path / "big.rrd"
    subprocess.run([sys.executable, "-c", BIG_SCRIPT, str(big), "170"], check=True, timeout=300)
    size = big.stat().st_size
    assert size > 250_000_000
    assert server.proc is not None
    small = tmp_path / "warmup.rrd"
    subprocess.run([sys.executable, "-c", BIG_SCRIPT.replace("big-upload", "warmup"), str(small), "2"], check=True)
    assert _fleet_upload(server, small).returncode == 0  # every code path loaded once
    before = _peak_rss(server.proc.pid)
    result = _fleet_upload(server, big)
    assert result.returncode == 0, result.stderr
    grew = _peak_rss(server.proc.pid) - before
    assert grew < 64 * 1024 * 1024, f"peak RSS grew by {grew / 1e6:.0f} MB for a {size / 1e6:.0f} MB body"
    assert (server.data_dir / "hot" / "big-upload" / "run.rrd").stat().st_size > size * 0.95


@pytest.mark.postgres
def test_postgres_catalog(tmp_path: Path, recordings: dict[str, Recording], request: pytest.FixtureRequest):
    url = request.getfixturevalue("empty_postgres_url")
    assert subprocess.run([FLEET, "db", "upgrade", "--catalog-url", url], capture_output=True).returncode == 0
    live = LiveServer(tmp_path / "pg-data", catalog_url=url).start()
    try:
        rec = recordings["properties"]
        assert _fleet_upload(live, rec.path).returncode == 0
        engine = sa.create_engine(url)
        with engine.connect() as conn:
            row = conn.execute(
                sa.text("select robot_id, status, chunks from runs where id = :id"),
                {"id": rec.recordings[0]["recording_id"]},
            ).one()
            entities = conn.execute(sa.text("select count(*) from run_entities")).scalar()
        engine.dispose()
        assert row.status == "closed" and row.chunks > 0 and entities == len(rec.recordings[0]["entities"])
    finally:
        live.stop()


def test_message_over_the_limit_is_413(tmp_path: Path, recordings: dict[str, Recording]):
    live = LiveServer(tmp_path / "small-limit", max_message_size="1000").start()
    try:
        response = httpx.post(f"{live.url}/v1/uploads", content=recordings["large"].data, timeout=60)
        assert response.status_code == 413
        assert response.json()["code"] == "MESSAGE_TOO_LARGE" and "FLEET_MAX_MESSAGE_SIZE" in response.json()["message"]
    finally:
        live.stop()
