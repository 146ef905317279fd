"""Writers of the embedded catalog never fail each other: DuckDB refuses ("Conflict on update!") a
transaction that updates a row another one changed after it began, so writers take turns."""

from __future__ import annotations

import datetime as dt
import threading
from pathlib import Path

import pytest
from sqlalchemy.orm import sessionmaker

from catalog import queries
from catalog.db import create_engine, session_scope, upgrade
from catalog.models import Run
from tests.catalog.records import run_record

T0 = dt.datetime(2026, 11, 22, 8, 0, tzinfo=dt.UTC)


def record(run_id: str, chunks: int) -> queries.RunRecord:
    return run_record(
        run_id,
        T0,
        status="live",
        ended_at=None,
        last_data_at=T0 + dt.timedelta(seconds=chunks),
        chunks=chunks,
        rows=chunks,
        bytes=chunks * 100,
        timelines=[queries.TimelineRecord("frame", "sequence", 0, chunks)],
    )


@pytest.mark.slow
def test_concurrent_writers_of_the_same_rows_all_succeed(tmp_path: Path):
    engine = create_engine(f"duckdb:///{tmp_path / 'catalog.duckdb'}")
    upgrade(engine)
    catalog = sessionmaker(engine)
    with session_scope(catalog, write=True) as session:
        queries.save_run(session, record("run-1", 0), T0)
    errors: list[BaseException] = []
    rounds = 20

    def ingest_flushes() -> None:  # what the housekeeping and an upload do: the run and its robot
        for n in range(1, rounds + 1):
            try:
                with session_scope(catalog, write=True) as session:
                    queries.save_run(session, record("run-1", n), T0 + dt.timedelta(seconds=n))
            except BaseException as exc:
                errors.append(exc)

    def user_pins() -> None:  # what a pin does, on the same row
        for n in range(rounds):
            try:
                with session_scope(catalog, write=True) as session:
                    run = session.get(Run, "run-1")
                    assert run is not None
                    run.pinned, run.pinned_by = n % 2 == 0, "bob@lab"
                    queries.add_event(session, "run-1", "pin", T0, "bob@lab", None)
            except BaseException as exc:
                errors.append(exc)

    threads = [threading.Thread(target=f) for f in (ingest_flushes, ingest_flushes, user_pins, user_pins)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert errors == []
    with session_scope(catalog) as session:
        assert len(queries.run_events(session, "run-1")) == 2 * rounds
    engine.dispose()
