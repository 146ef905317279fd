"""A hot run is read through any node: downloads and the agent's `held` question reaching a node
that does not own the run are answered by its owner, with the caller's own rights. Two real
`fleet serve` processes on one Postgres catalog, auth on."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import jwt
import pytest

from services.rrd.decoder import iter_events
from services.rrd.messages import ArrowMessage
from tests.conftest import fresh_catalog
from tests.services.cluster.two_nodes import bearer, chunk_count, node, recording, requests_of, token

pytestmark = [pytest.mark.slow, pytest.mark.sdk, pytest.mark.postgres]


@pytest.fixture
def nodes(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[object, object]]:
    with fresh_catalog("postgres", request, tmp_path) as url:
        a = node(tmp_path, "a", url, promote_after_s="3600").start()  # the run stays hot on A
        b = node(tmp_path, "b", url, promote_after_s="3600").start()
        try:
            yield a, b
        finally:
            a.kill()
            b.kill()


def test_a_hot_run_is_read_through_the_node_that_does_not_own_it(nodes: tuple, tmp_path: Path) -> None:  # type: ignore[type-arg]
    a, b = nodes
    robot, other_robot, reader = token(a, ["ingest"], "r1"), token(a, ["ingest"], "r2"), token(a, ["read"])
    path = recording(tmp_path, "run-r", 120)
    assert a.write_messages(requests_of(path), token=robot)[0].name == "OK"
    b.wait_for(
        lambda: httpx.get(f"{b.url}/v1/runs/run-r", headers=bearer(reader), timeout=10).json().get("owner") == "a",
        what="the run's row naming its owner",
    )

    # A stream of the same run reaching B is relayed to A whole: A skips every chunk it holds.
    before = a.metric("fleet_ingest_chunks_duplicate_total")
    assert b.write_messages(requests_of(path), token=robot)[0].name == "OK"
    chunks = chunk_count(path)
    a.wait_for(
        lambda: a.metric("fleet_ingest_chunks_duplicate_total") - before >= chunks,
        timeout=120,  # counted when the relayed stream ends at A; a loaded machine is slow to get there
        what="A to count the relayed stream's chunks as held",
    )
    counts = {
        f"{n.data_dir.name} {kind}": n.metric(f"fleet_ingest_chunks_{kind}_total")
        for n in (a, b)
        for kind in ("new", "duplicate")
    }
    assert counts["a duplicate"] - before == chunks and counts["a new"] == chunks, (chunks, before, counts)
    assert counts["b new"] == 0 and not (b.data_dir / "hot" / "run-r").exists(), counts

    url = "/v1/runs/run-r/recording.rrd?include=/metrics/**"
    from_a = httpx.get(a.url + url, headers=bearer(reader), timeout=30)
    from_b = httpx.get(b.url + url, headers=bearer(reader), timeout=30)
    assert from_a.status_code == from_b.status_code == 200, from_b.text
    assert from_b.content == from_a.content and len(from_b.content) > 1000
    served = tmp_path / "from-b.rrd"
    served.write_bytes(from_b.content)
    # the 120 scalars, and the static properties a download always keeps: every chunk of the run
    assert sum(isinstance(e, ArrowMessage) for e in iter_events(served)) == chunk_count(path)

    ids = [e.chunk_id.hex() for e in iter_events(path) if isinstance(e, ArrowMessage) and e.chunk_id]
    held_b = httpx.post(f"{b.url}/v1/runs/run-r/held", json={"chunk_ids": ids}, headers=bearer(robot), timeout=30)
    held_a = httpx.post(f"{a.url}/v1/runs/run-r/held", json={"chunk_ids": ids}, headers=bearer(robot), timeout=30)
    assert held_b.status_code == 200, held_b.text
    assert held_b.json() == held_a.json()
    assert held_b.json()["missing"] == [] and len(held_b.json()["unsealed"]) == len(ids)

    # Asked through B, the owner applies the caller's own rights: another robot's token is refused.
    refused = httpx.post(
        f"{b.url}/v1/runs/run-r/held", json={"chunk_ids": ids[:1]}, headers=bearer(other_robot), timeout=30
    )
    assert refused.status_code == 403, refused.text
    assert "r2" in refused.json()["message"]
    # A bad window is refused by the owner with its own status and reason.
    bad = httpx.get(f"{b.url}/v1/runs/run-r/recording.rrd?timeline=nope&start=1", headers=bearer(reader), timeout=30)
    assert bad.status_code == 422 or bad.status_code == 400, bad.text
    assert "nope" in bad.json()["message"]

    # A live run followed through B (streamed from its owner A) stops when the follower's token is
    # revoked: B, the node the follower reached, checks it (within its FLEET_AUTH_CACHE_S, 5 s).
    hang_up = threading.Event()
    live = requests_of(recording(tmp_path, "run-live", 50))

    def live_stream() -> Iterator[bytes]:  # the run stays live while it is followed
        yield from live
        hang_up.wait(120)

    writer = threading.Thread(target=a.write_messages, args=(live_stream(),), kwargs={"token": robot, "timeout": 180})
    writer.start()
    try:
        b.wait_for(
            lambda: (
                httpx.get(f"{b.url}/v1/runs/run-live", headers=bearer(reader), timeout=10).json().get("owner") == "a"
            ),
            what="the live run's row naming its owner",
        )
        follower = token(a, ["read"])
        ended, first = threading.Event(), threading.Event()

        def follow() -> None:
            url = f"{b.url}/v1/runs/run-live/recording.rrd?follow=true"
            with httpx.stream("GET", url, headers=bearer(follower), timeout=120) as response:
                for _ in response.iter_raw():
                    first.set()
            ended.set()

        threading.Thread(target=follow, daemon=True).start()
        assert first.wait(60), "nothing of the live run arrived through B"
        follower_id = jwt.decode(follower, options={"verify_signature": False})["jti"]
        assert httpx.delete(f"{a.url}/v1/tokens/{follower_id}", headers=a.headers, timeout=10).status_code == 200
        revoked = time.monotonic()
        assert ended.wait(30), "the follow through B went on after its token was revoked"
        assert time.monotonic() - revoked < 5.0 + 4.0  # B's cache of the token, a check, some slack
    finally:
        hang_up.set()
        writer.join(60)
