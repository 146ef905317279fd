"""A run's final values, once it is sealed.

Retention tells `Sealing.sealed` each run it sealed (after the catalog switch commits); a thread of
its own gives the run its final events and metrics: the live evaluator's, when it was fed every
wanted chunk of the sealed run in time order under the running rules, else the stored run evaluated
by ranged reads over its chunk index. In the same transaction the run's robot tags are made those of
its `fleet` property, and webhooks are told of the seal and of each new event. A failure is logged:
the run keeps its live values, and the rules backfill (which picks sealed runs whose values are
still live) finishes the work.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
from typing import Any

from sqlalchemy.orm import Session

from catalog import corpus as corpus_db
from catalog import queries, webhooks
from catalog.db import session_scope
from catalog.models import Event, Run
from catalog.webhooks import RUN_SEALED
from services.corpus.evaluation import (
    FINAL,
    SKIPPED,
    NotReadable,
    Reads,
    RunningRules,
    announce_events,
    evaluate_recording,
    open_run,
    properties_of,
    robot_tags,
    running_rules,
    wanted_rows,
    write_evaluation,
)
from services.corpus.live import HandedOver, LiveRules
from services.hot.read import HotRuns
from services.node import Node
from services.rules.evaluate import Evaluation

log = logging.getLogger(__name__)

_STOP = ""


class Sealing:
    """Final values for the runs this node seals, on a thread of its own (promotion never waits)."""

    def __init__(self, node: Node, live: LiveRules | None, hot: HotRuns | None, *, max_events: int) -> None:
        self.node, self.live, self.hot_runs, self.max_events = node, live, hot, max_events
        self.reads = Reads()  # what evaluating sealed runs read (the live evaluator's runs read nothing)
        self.from_live = 0  # runs whose final values came from the live evaluator
        self.failures = 0  # runs whose final values were not written (the backfill writes them)
        self._queue: queue.Queue[str] = queue.Queue()  # run ids: small, never bounded by ingest
        self._thread: threading.Thread | None = None

    def sealed(self, run_id: str) -> None:
        """Retention's `on_sealed`: the run's final values are given soon, on the sealing thread."""
        self._queue.put(run_id)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._work, name="fleet-rules-sealing", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        if self._thread is not None:
            self._queue.put(_STOP)
            self._thread.join(timeout=60)
            self._thread = None

    def _work(self) -> None:
        while (run_id := self._queue.get()) != _STOP:
            try:
                self.finalize(run_id)
            except Exception:  # the backfill picks the run up (its values are still live)
                self.failures += 1
                log.exception("final rules values of run %s not written; the rules backfill retries", run_id)

    def finalize(self, run_id: str) -> list[Event]:
        """Give a sealed run its final values; returns its new events."""
        handed = self.live.hand_over(run_id) if self.live is not None else None
        with session_scope(self.node.catalog) as session:
            running = running_rules(session)
            run = queries.require_run(session, run_id)
            session.expunge(run)
        try:
            evaluation = self._evaluate(run, running, handed)
        except NotReadable as exc:
            with session_scope(self.node.catalog, write=True) as session:
                corpus_db.set_evaluation_state(session, run_id, running.version, SKIPPED, exc.note, self.node.clock())
            return []
        with session_scope(self.node.catalog, write=True) as session:
            return finish_run(session, run, running.version, evaluation, self.node.clock())

    def _evaluate(self, run: Run, running: RunningRules, handed: HandedOver | None) -> Evaluation:
        properties = properties_of(run)
        recording = open_run(self.node, self.hot_runs, run, self.node.clock())
        try:
            rows = list(recording.index())
            live = handed.run if handed is not None and handed.version == running.version else None
            if live is not None and live.whole:
                wanted = {r.chunk_id for r in wanted_rows(rows, live.evaluator)}
                if wanted == live.seen:  # fed every wanted chunk of the sealed run: nothing to read
                    self.from_live += 1
                    return live.evaluator.finish(properties)
            return evaluate_recording(
                dataclasses.replace(recording, index=lambda: rows),
                running.rules,
                properties,
                max_events=self.max_events,
                reads=self.reads,
            )
        finally:
            recording.close()


def finish_run(session: Session, run: Run, version: int, evaluation: Evaluation, now: Any) -> list[Event]:
    """A sealed run's final values written, its robot tags synced, webhooks told: one transaction."""
    new = write_evaluation(session, run.id, run.robot_id, version, FINAL, evaluation, now)
    corpus_db.sync_robot_tags(session, run.id, robot_tags(properties_of(run)), now)
    webhooks.enqueue(session, RUN_SEALED, f"{RUN_SEALED}:{run.id}", run_payload(run))
    announce_events(session, new)
    return new


def run_payload(run: Run) -> dict[str, Any]:
    return {"run_id": run.id, "robot_id": run.robot_id, "tier": run.tier, "bytes": run.bytes}
