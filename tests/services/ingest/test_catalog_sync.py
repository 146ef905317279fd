"""`CatalogSync`: what ingest writes to the catalog, against the catalog itself (DuckDB and Postgres)."""

from __future__ import annotations

import datetime as dt
import uuid

import sqlalchemy as sa
from sqlalchemy.orm import sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.models import Dataset
from catalog.queries import EntityRecord, RunRecord, TimelineRecord
from services.ingest.catalog_sync import CatalogSync
from tests.catalog.records import run_record

NOW = dt.datetime(2026, 11, 23, 12, 0, tzinfo=dt.UTC)


def record(run_id: str) -> RunRecord:
    return run_record(
        run_id,
        NOW,
        robot_id="robot-sync",
        application_id="sync",
        status="live",
        ended_at=None,
        entities=[EntityRecord("/a", 1, 0, 1, 10, [], [])],
        timelines=[TimelineRecord("frame", "sequence", 0, 0)],
    )


def test_a_snapshot_taken_before_a_run_was_dropped_does_not_bring_it_back(engine: sa.Engine):
    factory = sessionmaker(engine)
    sync = CatalogSync(factory, clock=lambda: NOW)
    snapshot = record(f"run-{uuid.uuid4().hex[:8]}")
    try:
        sync.save([snapshot], runs={})
        with session_scope(factory) as session:
            assert queries.get_run(session, snapshot.id) is not None
        # The housekeeping took its snapshot, then a refusal dropped the run, and the snapshot is
        # saved only now: the run stays gone.
        sync.drop(snapshot.id)
        sync.save([snapshot], runs={})
        with session_scope(factory) as session:
            assert queries.get_run(session, snapshot.id) is None
            assert queries.run_entities(session, snapshot.id) == []
        assert not sync.dropped
    finally:  # the engine is shared by the session's tests: leave it as found
        with session_scope(factory, write=True) as session:
            queries.remove_hot_run(session, snapshot.id)
            session.execute(sa.delete(Dataset).where(Dataset.name == snapshot.application_id))
