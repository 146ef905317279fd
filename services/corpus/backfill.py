"""The rules backfill: every stored run evaluated under the running rules, once.

A run is due when it has no evaluation, one of another rules version, live values though it is
sealed (its sealing's evaluation failed), or was skipped while cold and is warm again. Each run is
read by ranged reads of the chunks the rules name (`evaluation.py`) and its values replaced in one
transaction, so the job is re-runnable and resumable after a kill: the catalog is its progress, and
a run at the running version is not read again. Reads are paced to `bytes_per_s`
(FLEET_RULES_BACKFILL_BYTES_S). A hot run of this node is evaluated from its file (its values stay
`live`: its sealing makes them final); one of another node is left to its sealing. Cold runs are
not read: their evaluation says so (skipped).

It runs in the one schedule (`services.retention.schedule`, handed in by the server) and now with
`fleet rules backfill` (`POST /v1/rules/backfill`), one at a time across the depot's processes.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog import corpus as corpus_db
from catalog.db import session_scope
from catalog.models import Run, RunEvaluation
from core.states import Tier
from services.corpus.evaluation import (
    LIVE,
    SKIPPED,
    NotReadable,
    Reads,
    RunningRules,
    announce_events,
    evaluate_run,
    running_rules,
    write_evaluation,
)
from services.corpus.sealing import finish_run
from services.hot.read import HotRuns
from services.node import Node
from services.retention.locks import job_lock

log = logging.getLogger(__name__)

JOB = "rules-backfill"
Emit = Callable[[dict[str, Any]], None]


@dataclass
class Summary:
    total: int = 0
    evaluated: int = 0
    skipped_cold: int = 0
    skipped: int = 0  # hot on another node: its sealing evaluates it
    failed: int = 0
    bytes_read: int = 0
    failures: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "total": self.total,
            "evaluated": self.evaluated,
            "skipped_cold": self.skipped_cold,
            "skipped": self.skipped,
            "failed": self.failed,
            "bytes_read": self.bytes_read,
        }


class Pace:
    """Sleeps enough after each read that the reads average at most `bytes_per_s`."""

    def __init__(self, bytes_per_s: int, sleep: Callable[[float], None] = time.sleep) -> None:
        self.bytes_per_s, self.sleep = bytes_per_s, sleep
        self.started = time.monotonic()
        self.read = 0

    def __call__(self, size: int) -> None:
        self.read += size
        ahead = self.read / self.bytes_per_s - (time.monotonic() - self.started)
        if ahead > 0:
            self.sleep(ahead)


@dataclass
class RulesBackfill:
    """What the backfill works with, built once by the server (or a test)."""

    node: Node
    hot_runs: HotRuns | None
    max_events: int
    bytes_per_s: int
    sleep: Callable[[float], None] = time.sleep

    def run(self, emit: Emit | None = None) -> Summary | None:
        """Evaluate every due run; None if another process runs the backfill now."""
        bind = self.node.catalog.kw["bind"]
        assert isinstance(bind, sa.Engine)
        with job_lock(bind, JOB) as got:
            if not got:
                if emit is not None:
                    emit({"event": "busy", "detail": "the rules backfill is running in another process; try again"})
                return None
            return self._run(emit or (lambda _: None))

    def _run(self, emit: Emit) -> Summary:
        with session_scope(self.node.catalog) as session:
            running = running_rules(session)
            due = due_runs(session, running.version)
        summary = Summary(total=len(due))
        emit({"event": "plan", "total": len(due), "rules_version": running.version})
        reads = Reads(pace=Pace(self.bytes_per_s, self.sleep))
        for run_id in due:
            before = reads.bytes_read
            outcome, detail = self._one(run_id, running, reads, summary)
            read = reads.bytes_read - before
            emit({"event": "run", "run": run_id, "outcome": outcome, "ok": outcome != "failed", "detail": detail})
            log.info("rules backfill: run %s %s (%s, %d bytes read)", run_id, outcome, detail, read)
        summary.bytes_read = reads.bytes_read
        emit({"event": "end", **summary.to_dict()})
        if summary.total:
            log.info("rules backfill (version %d): %s", running.version, summary.to_dict())
        return summary

    def _one(self, run_id: str, running: RunningRules, reads: Reads, summary: Summary) -> tuple[str, str]:
        try:
            run, evaluation = evaluate_run(
                self.node, self.hot_runs, run_id, running, max_events=self.max_events, reads=reads
            )
        except NotReadable as exc:
            if not exc.skipped:
                summary.skipped += 1
                return "skipped", exc.note
            with session_scope(self.node.catalog, write=True) as session:
                corpus_db.set_evaluation_state(session, run_id, running.version, SKIPPED, exc.note, self.node.clock())
            summary.skipped_cold += 1
            return "skipped", exc.note
        except Exception as exc:  # reported per run; the next backfill retries it
            summary.failed += 1
            summary.failures.append(run_id)
            log.warning("rules backfill of run %s failed: %s", run_id, exc)
            return "failed", f"{type(exc).__name__}: {exc}"
        now = self.node.clock()
        with session_scope(self.node.catalog, write=True) as session:
            if run.tier == Tier.HOT:  # still growing: its sealing makes the values final
                new = write_evaluation(session, run.id, run.robot_id, running.version, LIVE, evaluation, now)
                announce_events(session, new)
                state = LIVE
            else:
                finish_run(session, run, running.version, evaluation, now)
                state = "final"
        summary.evaluated += 1
        return "evaluated", f"{state}, {len(evaluation.events)} events, {len(evaluation.metrics)} metrics"


def due_runs(session: Session, version: int) -> list[str]:
    """The runs the backfill evaluates, newest first."""
    evaluation = RunEvaluation
    stmt = (
        sa.select(Run.id)
        .outerjoin(evaluation, evaluation.run_id == Run.id)
        .where(Run.tier != Tier.DELETED)
        .where(
            sa.or_(
                evaluation.run_id.is_(None),
                evaluation.rules_version != version,
                sa.and_(evaluation.state == LIVE, Run.tier != Tier.HOT),
                sa.and_(evaluation.state == SKIPPED, Run.tier == Tier.WARM),
            )
        )
        .order_by(Run.last_data_at.desc(), Run.id)
    )
    return list(session.scalars(stmt))
