"""A node that pauses (a long GC pause, a partition) past its lease loses its run to the node that
received the run's next chunks; when it wakes it must not seal the run (its sealing commit is
fenced by the lease's epoch) but hand its hot copy to the new owner, which keeps each chunk once
and seals the run once. Two real `fleet serve` processes on one Postgres catalog, auth on."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import sqlalchemy as sa

from tests.conftest import fresh_catalog
from tests.services.cluster.two_nodes import bearer, chunk_count, node, recording, requests_of, token
from tests.services.ingest.live_server import LiveServer

pytestmark = [pytest.mark.slow, pytest.mark.sdk, pytest.mark.postgres]


@pytest.fixture
def catalog_url(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    with fresh_catalog("postgres", request, tmp_path) as url:
        yield url


def _alive(node: LiveServer, ask: LiveServer) -> bool:
    listed = httpx.get(f"{ask.url}/v1/nodes", headers=ask.headers, timeout=10).json()["nodes"]
    return any(n["id"] == node.settings["node_id"] and n["alive"] for n in listed)


def test_a_paused_owner_hands_its_copy_over_and_the_run_is_sealed_once(tmp_path: Path, catalog_url: str) -> None:
    a = node(tmp_path, "a", catalog_url, promote_after_s="3").start()
    b = node(tmp_path, "b", catalog_url, promote_after_s="3").start()
    try:
        robot = token(a, ["ingest"], "r1")
        path = recording(tmp_path, "run-p", 300)
        requests = requests_of(path)
        chunks = chunk_count(path)

        # The first part of the run reaches node A, which owns it from then on.
        assert a.write_messages(requests[: len(requests) // 2], token=robot)[0].name == "OK"
        a.wait_for(lambda: (a.data_dir / "hot" / "run-p").is_dir(), what="A holds the run hot")

        os.kill(a.proc.pid, signal.SIGSTOP)  # A stops heart-beating, holding its copy and its lease
        try:
            b.wait_for(lambda: not _alive(a, b), timeout=30, what="A's lease to run out")
            answer = httpx.post(
                f"{b.url}/v1/uploads",
                content=path.read_bytes(),
                headers=bearer(robot),
                timeout=60,
            )
            assert answer.status_code == 200, answer.text
            assert answer.json()["chunks_new"] == chunks  # B took the run over and filed it whole
        finally:
            os.kill(a.proc.pid, signal.SIGCONT)

        # A wakes up: its copy goes to B, never into the warm tier by A's hand.
        a.wait_for(lambda: not (a.data_dir / "hot" / "run-p").exists(), timeout=60, what="A to hand its copy over")
        b.wait_for(
            lambda: httpx.get(f"{b.url}/v1/runs/run-p", headers=b.headers, timeout=10).json().get("tier") == "warm",
            timeout=60,
            what="the run to be sealed",
        )
        run = httpx.get(f"{b.url}/v1/runs/run-p", headers=b.headers, timeout=10).json()
        assert run["chunks"] == chunks and run["owner"] is None
        engine = sa.create_engine(catalog_url)
        try:
            with engine.connect() as conn:
                promotions = conn.execute(
                    sa.text("SELECT count(*) FROM retention_events WHERE run_id = 'run-p' AND action = 'promote'")
                ).scalar_one()
        finally:
            engine.dispose()
        assert promotions == 1
        log_a = a.log.read_text()
        assert "taken over by another node" in log_a or "owned by another node now" in log_a
        assert "handed to node b" in log_a
    finally:
        a.kill()
        b.kill()
