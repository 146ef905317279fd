"""A hundred viewers following a live run (`recording.rrd?follow=true`) cost the server no thread
each: the catalog endpoints answer as fast as without them, and every follower gets the chunks
written after it connected and a stream that ends, with its footer, when the run closes."""

from __future__ import annotations

import asyncio
import contextlib
import io
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest

from services.rrd import ArrowMessage, iter_events
from services.rrd.footer import read_footer
from tests.services.ingest.live_server import LiveServer, start_robot
from tests.services.rrd.recordings import rerun_rrd_ok

pytestmark = pytest.mark.sdk
FOLLOWERS = 100  # more than the 40 worker threads Starlette runs sync handlers and sync bodies on
SAMPLES = 20
REQUEST_TIMEOUT_S = 5.0  # a catalog request that takes longer counts as this long


@pytest.fixture
def server(tmp_path: Path) -> Iterator[LiveServer]:
    live = LiveServer(tmp_path / "data", catalog_flush_s="0.2", close_after_s="600").start()
    yield live
    live.stop()


def chunk_ids(data: bytes) -> set[bytes]:
    return {e.chunk_id for e in iter_events(io.BytesIO(data)) if isinstance(e, ArrowMessage) and e.chunk_id}


async def catalog_p95(client: httpx.AsyncClient, run_id: str) -> float:
    """The 95th percentile latency of GET /v1/runs and GET /v1/runs/RUN, asked one after another."""
    paths = ["/v1/runs", f"/v1/runs/{run_id}"] * SAMPLES
    rank = int(len(paths) * 0.95) - 1
    latencies = []
    for path in paths:
        started = time.monotonic()
        try:
            response = await client.get(path, timeout=REQUEST_TIMEOUT_S)
            assert response.status_code == 200, response.text
            latencies.append(time.monotonic() - started)
        except httpx.TimeoutException:
            latencies.append(REQUEST_TIMEOUT_S)
            if latencies.count(REQUEST_TIMEOUT_S) > len(paths) - 1 - rank:
                return REQUEST_TIMEOUT_S  # already more timeouts than the 95th percentile leaves out
    return sorted(latencies)[rank]


class Follower:
    def __init__(self) -> None:
        self.received = bytearray()
        self.first_bytes = asyncio.Event()
        self.ended = False

    async def follow(self, client: httpx.AsyncClient, run_id: str) -> None:
        async with client.stream(
            "GET", f"/v1/runs/{run_id}/recording.rrd", params={"follow": "true"}, timeout=120
        ) as response:
            assert response.status_code == 200
            async for piece in response.aiter_raw():
                self.received.extend(piece)
                self.first_bytes.set()
        self.ended = True


@dataclass
class Observed:
    followers: list[Follower]
    all_connected: bool
    still_open: bool  # no follower's stream ended while the run was live
    before: set[bytes] = field(default_factory=set)  # the run's chunks when the followers had connected
    after: set[bytes] = field(default_factory=set)  # and once it closed


def test_a_hundred_followers_of_a_live_run_do_not_slow_the_catalog(server: LiveServer, tmp_path: Path, rerun_bin: str):
    copy, run_id = tmp_path / "copy.rrd", "followed-by-many"
    robot = start_robot("live", server.grpc_url, str(copy), run_id)
    assert robot.stdout is not None and robot.stdin is not None
    assert robot.stdout.readline().strip() == "READY"  # ten frames sent, the stream stays open
    server.wait_for(
        lambda: httpx.get(f"{server.url}/v1/runs/{run_id}", timeout=10).status_code == 200,
        what="the live run in the catalog",
    )

    async def scenario() -> Observed:
        async with (
            httpx.AsyncClient(base_url=server.url) as catalog,
            httpx.AsyncClient(base_url=server.url, limits=httpx.Limits(max_connections=FOLLOWERS)) as viewers,
        ):
            baseline = await catalog_p95(catalog, run_id)
            followers = [Follower() for _ in range(FOLLOWERS)]
            tasks = [asyncio.create_task(f.follow(viewers, run_id)) for f in followers]
            with contextlib.suppress(TimeoutError):  # asserted below, after the latencies that say why
                await asyncio.wait_for(asyncio.gather(*(f.first_bytes.wait() for f in followers)), 30)
            with_followers = await catalog_p95(catalog, run_id)
            assert with_followers < max(10 * baseline, 1.0), (
                f"catalog p95 {with_followers:.3f}s with {FOLLOWERS} followers, {baseline:.3f}s without"
            )
            observed = Observed(
                followers,
                all_connected=all(f.first_bytes.is_set() for f in followers),
                still_open=not any(f.ended for f in followers),
            )
            observed.before = chunk_ids((await catalog.get(f"/v1/runs/{run_id}/recording.rrd", timeout=60)).content)
            assert robot.stdin is not None
            robot.stdin.write("go\n")  # ten frames more, then the stream ends and the run closes
            robot.stdin.flush()
            _, err = await asyncio.to_thread(robot.communicate, timeout=120)
            assert robot.returncode == 0, err
            await asyncio.wait_for(asyncio.gather(*tasks), 60)
            observed.after = chunk_ids((await catalog.get(f"/v1/runs/{run_id}/recording.rrd", timeout=60)).content)
            return observed

    try:
        seen = asyncio.run(scenario())
    finally:
        if robot.poll() is None:  # the test failed before the robot finished
            robot.kill()
            robot.communicate()
    assert seen.all_connected, "not every follower received the run so far"
    assert seen.still_open, "a follower's stream ended while the run was live"
    assert seen.before < seen.after  # chunks were written after the followers connected
    for follower in seen.followers:
        data = bytes(follower.received)
        assert follower.ended and chunk_ids(data) == seen.after  # every chunk, the later ones too
        footer = read_footer(io.BytesIO(data))  # the stream ends with End and a valid footer
        assert footer is not None and footer.manifests
    out = tmp_path / "followed.rrd"
    out.write_bytes(bytes(seen.followers[0].received))
    rerun_rrd_ok(rerun_bin, "verify", out)
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", copy, out)
