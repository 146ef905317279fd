"""`fleet serve` with rules: a robot streams the scene with the real rerun-sdk; its events and
metrics are there while it is hot, final once sealed; `fleet rules backfill` (POST
/v1/rules/backfill, write scope) re-evaluates it after a rules change."""

from __future__ import annotations

import datetime as dt

import httpx
import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus as corpus_db
from catalog.db import session_scope
from catalog.models import RunEvaluation
from tests.services.corpus.pipeline import scene as expect
from tests.services.corpus.pipeline.conftest import Served, ServeFactory
from tests.waiting import wait_for

RUN = "corpus-e2e"
pytestmark = pytest.mark.postgres


@pytest.fixture
def depot(serve: ServeFactory) -> Served:
    """A server on a Postgres catalog the test reads too, running the scene's rules."""
    return serve(rules=expect.RULES_V1)


def evaluation(catalog: sessionmaker[Session]) -> tuple[str, int] | None:
    with session_scope(catalog) as session:
        found = session.get(RunEvaluation, RUN)
        return (found.state, found.rules_version) if found is not None else None


def interventions(catalog: sessionmaker[Session]) -> list[tuple[int, int]]:
    with session_scope(catalog) as session:
        return sorted(
            (e.range_start, e.range_end) for e in corpus_db.events_of_run(session, RUN) if e.kind == "intervention"
        )


def test_streamed_run_live_then_sealed_then_backfilled(depot: Served):
    server, catalog = depot.server, depot.catalog
    robot = depot.stream_scene(RUN, depot.token("ingest", robot="robot-c"))
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

    writer = depot.token("write")
    wait_for(lambda: depot.promoted(RUN, writer), timeout=60, what="the run promoted")
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

    reader = {"Authorization": f"Bearer {depot.token('read')}"}
    assert httpx.post(f"{server.url}/v1/rules/backfill", timeout=30).status_code == 401
    assert httpx.post(f"{server.url}/v1/rules/backfill", headers=reader, timeout=30).status_code == 403

    out = depot.fleet(writer, "rules", "backfill")
    assert "1 runs evaluated, 0 skipped (cold)" in out.stdout and "0 failed" in out.stdout
    assert f"evaluated {RUN}" in out.stderr
    assert evaluation(catalog) == ("final", version)
    assert interventions(catalog) == expect.expected_interventions()  # replaced, not doubled
    with session_scope(catalog) as session:
        assert [m.name for m in corpus_db.metrics_of(session, RUN)] == ["temp_max"]
