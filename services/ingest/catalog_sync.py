"""Ingest's runs into the catalog: snapshots of what changed, written in one transaction, and a
record the catalog refuses retried on its own with backoff, so one bad run never holds back the
others. Runs' `dirty`, `catalog_failures` and `catalog_retry_at` say where each run stands."""

from __future__ import annotations

import datetime as dt
import logging
import threading
from collections.abc import Callable

from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.queries import RunRecord
from core.backoff import backoff_delay
from core.errors import CATALOG_DOWN
from services.ingest.run import IngestRun

log = logging.getLogger("services.ingest.service")

BACKOFF_FIRST = dt.timedelta(seconds=2)
BACKOFF_MAX = dt.timedelta(minutes=5)


class CatalogSync:
    def __init__(self, catalog: sessionmaker[Session] | None, clock: Callable[[], dt.datetime]) -> None:
        self.catalog = catalog
        self.clock = clock
        self._writes = threading.Lock()  # one catalog writer at a time for ingest's own records
        self.dropped: set[str] = set()  # hot runs dropped by ingest, removed from the catalog at the next save

    def take(self, runs: dict[str, IngestRun], default_robot: str, *, owned_only: bool = False) -> list[RunRecord]:
        """Snapshots of the runs that changed since the last flush (cheap: taken on the ingest
        thread, then saved with `save`, which may run on another thread). A run whose record the
        catalog refused waits for its retry time alone. `owned_only`: many nodes share the catalog,
        and a run's row is written by its owner only (a copy to hand over waits, dirty)."""
        records = []
        now = self.clock()
        for run in list(runs.values()):
            if owned_only and run.lease is None:
                continue
            if run.dirty and (run.catalog_retry_at is None or run.catalog_retry_at <= now):
                run.dirty = False
                records.append(run.record(default_robot))
        return records

    def drop(self, run_id: str) -> None:
        """Ingest dropped this hot run: its catalog row (if a save got there first) goes at the next
        save, after any save of it already under way."""
        self.dropped.add(run_id)

    def save(self, records: list[RunRecord], runs: dict[str, IngestRun]) -> None:
        """One transaction for all; if the catalog refuses it for one record's sake, each record on
        its own, so one bad run never holds back the others (it is retried with backoff)."""
        if self.catalog is None:
            return
        with self._writes:
            if self.dropped:
                # A snapshot taken before a run was dropped must not write it back after its removal.
                kept = [record for record in records if record.id not in self.dropped]
                self.mark_dirty([record for record in records if record.id in self.dropped], runs)
                records = kept
                self._remove_dropped()
            if not records:
                return
            try:
                self._save(records)
            except CATALOG_DOWN:
                self.mark_dirty(records, runs)
                raise
            except Exception:  # a record the catalog refuses: find which
                for record in records:
                    self._save_one(record, runs)
                return
        for record in records:
            run = runs.get(record.id)
            if run is not None:
                run.catalog_failures, run.catalog_retry_at = 0, None

    def _save(self, records: list[RunRecord]) -> None:
        assert self.catalog is not None
        now = self.clock()
        with session_scope(self.catalog, write=True) as session:
            for record in records:
                queries.save_run(session, record, now)

    def _remove_dropped(self) -> None:
        """(With `_writes` held.)"""
        assert self.catalog is not None
        gone = set(self.dropped)
        with session_scope(self.catalog, write=True) as session:
            for run_id in gone:
                queries.remove_hot_run(session, run_id)
        self.dropped -= gone

    def _save_one(self, record: RunRecord, runs: dict[str, IngestRun]) -> None:
        run = runs.get(record.id)
        try:
            self._save([record])
        except Exception as exc:  # logged and retried; never stops the other runs
            if run is None:
                return
            run.dirty = True
            run.catalog_failures += 1
            wait = _retry_wait(run.catalog_failures)
            run.catalog_retry_at = self.clock() + wait
            log.error(
                "the catalog refused the record of run %s (%s: %s); retrying in %s",
                record.id,
                type(exc).__name__,
                str(exc).splitlines()[0][:300] if str(exc) else "",
                wait,
            )
            return
        if run is not None:
            run.catalog_failures, run.catalog_retry_at = 0, None

    @staticmethod
    def mark_dirty(records: list[RunRecord], runs: dict[str, IngestRun]) -> None:
        """Written again at the next flush."""
        for record in records:
            run = runs.get(record.id)
            if run is not None:
                run.dirty = True  # retried at the next flush


def _retry_wait(failures: int) -> dt.timedelta:
    """How long a run whose record the catalog refused `failures` times in a row waits alone."""
    seconds = backoff_delay(failures, first=BACKOFF_FIRST.total_seconds(), cap=BACKOFF_MAX.total_seconds())
    return dt.timedelta(seconds=seconds)
