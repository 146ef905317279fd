"""`fleet serve` with rules: a robot streams the scene with the real rerun-sdk; its events and
metrics are there while it is hot, final once sealed; `fleet rules backfill` (POST
/v1/rules/backfill, write scope) re-evaluates it after a rules change."""

from __future__ import annotations

import datetime as dt
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus as corpus_db
from catalog.db import create_engine, session_scope
from catalog.models import RunEvaluation
from tests.conftest import fresh_catalog
from tests.services.corpus.pipeline import scene as expect
from tests.services.corpus.pipeline.conftest import CHUNK_ROWS, SCENE
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.waiting import wait_for

RUN = "corpus-e2e"
pytestmark = pytest.mark.postgres


@pytest.fixture
def depot(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[LiveServer, sessionmaker[Session]]]:
    """A server on a Postgres catalog the test reads too, running the scene's rules."""
    with fresh_catalog("postgres", request, tmp_path) as url:
        engine = create_engine(url)
        catalog = sessionmaker(engine)
        with session_scope(catalog, write=True) as session:
            corpus_db.add_rules_version(session, expect.RULES_V1, "test", dt.datetime.now(dt.UTC))
        server = LiveServer(
            tmp_path / "data",
            auth="on",
            catalog_url=url,
            scheduler="false",
            catalog_flush_s="0.2",
            promote_after_s="3600",
        ).start()
        try:
            yield server, catalog
        finally:
            server.stop()
            engine.dispose()


def token(server: LiveServer, *scopes: str, robot: str | None = None) -> str:
    body = {"scopes": list(scopes), "name": f"test-{'-'.join(scopes)}", "robot": robot}
    answer = httpx.post(f"{server.url}/v1/tokens", json=body, headers=server.headers, timeout=30)
    assert answer.status_code == 201, answer.text
    return str(answer.json()["token"])


def evaluation(catalog: sessionmaker[Session]) -> tuple[str, int] | None:
    with session_scope(catalog) as session:
        found = session.get(RunEvaluation, RUN)
        return (found.state, found.rules_version) if found is not None else None


def interventions(catalog: sessionmaker[Session]) -> list[tuple[int, int]]:
    with session_scope(catalog) as session:
        return sorted(
            (e.range_start, e.range_end) for e in corpus_db.events_of_run(session, RUN) if e.kind == "intervention"
        )


def test_streamed_run_live_then_sealed_then_backfilled(depot: tuple[LiveServer, sessionmaker[Session]]):
    server, catalog = depot
    env = {**os.environ, "RERUN_FLUSH_NUM_ROWS": CHUNK_ROWS, "FLEET_TOKEN": token(server, "ingest", robot="robot-c")}
    robot = subprocess.Popen(
        [sys.executable, SCENE, f"grpc:{server.grpc_url}", RUN],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert robot.stdout is not None and robot.stdin is not None
    try:
        assert robot.stdout.readline().strip() == "READY"  # frames 0-29: one drop over, one under way
        wait_for(lambda: len(interventions(catalog)) == 1, timeout=60, what="the live run's first event")
        assert evaluation(catalog) == ("live", 1)
        assert interventions(catalog) == expect.expected_interventions()[:1]
        robot.stdin.write("go\n")
        robot.stdin.flush()
        assert robot.wait(timeout=120) == 0
    finally:
        robot.kill()

    writer = {"Authorization": f"Bearer {token(server, 'write')}"}

    def promoted() -> bool:
        answer = httpx.post(f"{server.url}/v1/runs/{RUN}/promote", headers=writer, timeout=60)
        return answer.status_code == 200  # 409 while its stream is still open

    wait_for(promoted, timeout=60, what="the run promoted")
    wait_for(lambda: evaluation(catalog) == ("final", 1), timeout=60, what="final values")
    assert interventions(catalog) == expect.expected_interventions()
    with session_scope(catalog) as session:
        metrics = {m.name: m.value for m in corpus_db.metrics_of(session, RUN)}
        tags = {t.tag: t.added_by for t in corpus_db.tags_of(session, RUN)}
    with session_scope(catalog, write=True) as session:
        version = corpus_db.add_rules_version(session, expect.RULES_V2, "test", dt.datetime.now(dt.UTC))[0].version
    assert metrics["distance_m"] == pytest.approx(expect.expected_distance())
    assert metrics["temp_mean"] == pytest.approx(expect.expected_temp_mean())
    assert tags == {"night-shift": "robot", "dock-2": "robot"}

    reader = {"Authorization": f"Bearer {token(server, 'read')}"}
    assert httpx.post(f"{server.url}/v1/rules/backfill", timeout=30).status_code == 401
    assert httpx.post(f"{server.url}/v1/rules/backfill", headers=reader, timeout=30).status_code == 403

    out = subprocess.run(
        [FLEET, "rules", "backfill", "--api-url", server.url],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "FLEET_TOKEN": writer["Authorization"].removeprefix("Bearer ")},
    )
    assert out.returncode == 0, out.stderr
    assert "1 runs evaluated, 0 skipped (cold)" in out.stdout and "0 failed" in out.stdout
    assert f"evaluated {RUN}" in out.stderr
    assert evaluation(catalog) == ("final", version)
    assert interventions(catalog) == expect.expected_interventions()  # replaced, not doubled
    with session_scope(catalog) as session:
        assert [m.name for m in corpus_db.metrics_of(session, RUN)] == ["temp_max"]
