"""The rules, live: hot runs evaluated as their chunks arrive.

Ingest tells `LiveRules` (its `ChunkObserver`) of each new recording chunk an entity of which a rule
names; `chunk` puts it on a bounded queue and returns. One worker thread takes the chunks off (in
batches, every `BATCH_S`) and keeps a `RunEvaluator` per hot run (at most `max_runs`, the least
recently fed evicted); every `flush_s` it writes each changed run's events and metrics so far
(`state="live"`): at once when it has new events, every `METRICS_EVERY` flushes when only its metrics
moved. Ingest never waits: a full queue drops the chunk, and the run's live result no longer counts
as whole (its sealing evaluates the stored run).

A run ingest starts here is announced (`started`, queued before its first chunk): its evaluator starts
empty. Any other run's evaluator starts from the run's hot file as it stands (its wanted chunks read
through the chunk index), and afterwards skips the chunks it holds already: a run first seen after a restart,
an eviction or a rules change is still evaluated from its start. At sealing, `hand_over` gives the
run's evaluator to the sealing (through the queue, behind the run's last chunks), with the ids of
the chunks it was fed: it gives the final values only if those are every wanted chunk of the
sealed run.

The running rules are re-read from the catalog every `flush_s`; a new version resets the hot runs'
evaluators (each starts again from its file with its next chunk).

Each new event a `[[trigger]]` of the running rules names gets a trigger pull, queued in the same
transaction that writes it (`services.edge.triggers.queue_trigger_pulls`: the window around it, or a
pending pull of the run widened to take it): the robot's agent sends that window's full data.
"""

from __future__ import annotations

import datetime as dt
import logging
import threading
import time
from collections import OrderedDict, deque
from concurrent.futures import Future
from dataclasses import dataclass, field

from cachetools import FIFOCache
from sqlalchemy.orm import Session

from catalog import queries
from catalog.corpus import EvaluationFacts, current_rules, replace_evaluations
from catalog.db import session_scope
from catalog.models import Event, Run
from core.states import Tier
from services.corpus.evaluation import (
    LIVE,
    NO_RULES_VERSION,
    RunningRules,
    announce_events,
    evaluation_facts,
    properties_of,
    running_rules,
    wanted_rows,
)
from services.edge.triggers import DEPOT, queue_trigger_pulls, trigger_pulls_made
from services.hot.read import HotRuns
from services.node import Node
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.messages import ArrowMessage
from services.rules.evaluate import Evaluation, FoundEvent, RunEvaluator
from services.rules.spec import RuleSet
from services.runs.indexed import open_hot, read_events

log = logging.getLogger(__name__)

QUEUE_CHUNKS = 4096  # chunks waiting for the worker; past it they are dropped (the run is not whole)
# The worker takes what is queued in batches, this often: woken for each chunk, its thread and
# ingest's would contend for the interpreter at every chunk (ingest costs a third more beside it).
BATCH_S = 0.25
# A hot run whose only change is its metrics' values is written every this many flushes (new events
# at the next flush): each write replaces the run's values in the catalog, the worker's main cost.
METRICS_EVERY = 5
MAX_RUNS = 256  # hot runs with an evaluator at once
_WANTED_PATHS = 65536  # entity paths whose answer is remembered (cleared when full)
_GAVE_UP = 4096  # runs remembered as not whole (evicted, or chunks dropped)
HAND_OVER_S = 60.0  # sealing waits this long for the worker to hand a run over


@dataclass
class HotRun:
    """One hot run as the worker evaluates it."""

    run_id: str
    robot_id: str
    version: int
    evaluator: RunEvaluator
    seen: set[bytes] = field(default_factory=set)  # ids of the chunks fed to the evaluator
    events: list[FoundEvent] = field(default_factory=list)  # complete ones so far
    changed: bool = True
    whole: bool = True  # fed every wanted chunk from the run's start
    events_written: int | None = None  # how many of `events` its last write held (None: never written)
    flushes_unwritten: int = 0  # flushes since its last write that found only metrics changed


@dataclass(frozen=True)
class HandedOver:
    """What sealing takes of a hot run: its evaluator (None: the worker had none) and whether it was
    fed every wanted chunk it was told of."""

    version: int
    run: HotRun | None


@dataclass(frozen=True)
class _Chunk:
    run_id: str
    robot_id: str
    msg: ArrowMessage
    meta: ChunkMeta


@dataclass(frozen=True)
class _Started:
    run_id: str
    robot_id: str


@dataclass(frozen=True)
class _HandOver:
    run_id: str
    answer: Future[HandedOver]


_STOP = object()


@dataclass(frozen=True)
class _Filter:
    """Which entity paths the running rules want, remembered: swapped whole on a rules change."""

    probe: RunEvaluator
    wanted: dict[str, bool]


class LiveRules:
    """The ChunkObserver of a node's ingest: the running rules over its hot runs."""

    def __init__(
        self,
        node: Node,
        *,
        max_events: int,
        flush_s: float,
        queue_chunks: int = QUEUE_CHUNKS,
        max_runs: int = MAX_RUNS,
    ) -> None:
        self.node = node
        self.hot_runs: HotRuns | None = None  # the node's ingest, set once it is built (the hot files)
        self.max_events = max_events
        self.flush_s = flush_s
        self.max_runs = max_runs
        self.dropped_chunks = 0  # chunks not evaluated live because the queue was full
        self.evaluated_chunks = 0  # chunks fed to a run's evaluator (the worker's alone)
        self.cpu_s = 0.0  # the worker's CPU time: evaluating and writing (the rules' cost to the node)
        self.queue_chunks = queue_chunks
        self._queue: deque[object] = deque()  # chunks, then hand-overs and the stop, in order
        self._wake = threading.Event()  # a hand-over or the stop: take the queue now
        self._running = RunningRules(NO_RULES_VERSION, RuleSet.empty())
        self._filter = _Filter(RunEvaluator(self._running.rules, max_events=max_events), {})
        self._runs: OrderedDict[str, HotRun] = OrderedDict()  # the worker's alone
        self._gave_up: FIFOCache[str, bool] = FIFOCache(_GAVE_UP)  # not whole; the worker's alone
        self._overflowed: set[str] = set()  # runs whose chunks were dropped (from ingest's thread)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    # --- the ChunkObserver: on ingest's thread, never blocking -------------------------------

    def wants(self, entity_path: str) -> bool:
        known = self._filter
        wanted = known.wanted.get(entity_path)
        if wanted is None:
            if len(known.wanted) >= _WANTED_PATHS:
                known.wanted.clear()
            wanted = known.wanted[entity_path] = known.probe.wants(entity_path)
        return wanted

    def chunk(self, run_id: str, robot_id: str, msg: ArrowMessage, meta: ChunkMeta) -> None:
        if len(self._queue) >= self.queue_chunks:
            with self._lock:
                self._overflowed.add(run_id)
                self.dropped_chunks += 1
            return
        self._queue.append(_Chunk(run_id, robot_id, msg, meta))  # no wake-up: the worker comes by

    def started(self, run_id: str, robot_id: str) -> None:
        if len(self._queue) < self.queue_chunks:  # (else its first chunk reads the file from its start)
            self._queue.append(_Started(run_id, robot_id))

    # --- running --------------------------------------------------------------------------

    def start(self) -> None:
        """Read the running rules and start the worker."""
        self.reload_rules()
        self._thread = threading.Thread(target=self._work, name="fleet-live-rules", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Write what changed and stop the worker."""
        if self._thread is None:
            return
        self._queue.append(_STOP)
        self._wake.set()
        self._thread.join(timeout=30)
        self._thread = None

    @property
    def version(self) -> int:
        return self._running.version

    def hand_over(self, run_id: str, timeout_s: float = HAND_OVER_S) -> HandedOver | None:
        """The run's evaluator, once the worker has taken every chunk queued before (the run is
        sealed: no more come). None if the worker does not answer in time."""
        if self._thread is None:
            return None
        answer: Future[HandedOver] = Future()
        self._queue.append(_HandOver(run_id, answer))
        self._wake.set()
        try:
            return answer.result(timeout_s)
        except TimeoutError:
            log.warning("live rules did not hand run %s over in time: it is evaluated from its data", run_id)
            return None

    # --- the worker -------------------------------------------------------------------------

    def _work(self) -> None:
        next_tick = time.monotonic() + self.flush_s
        cpu_before = time.thread_time() - self.cpu_s
        while True:
            self._wake.wait(min(BATCH_S, max(0.0, next_tick - time.monotonic())))
            self._wake.clear()  # (what is queued before a later set is taken below)
            chunks: list[_Chunk] = []  # taken together: each run's evaluated as one batch
            while self._queue:
                item = self._queue.popleft()
                if isinstance(item, _Chunk):
                    chunks.append(item)
                    if len(chunks) < self.queue_chunks:  # (a queue that never empties: bounded batches)
                        continue
                self._add_batch(chunks)  # what came before a hand-over or the stop, first
                chunks = []
                if item is _STOP:
                    self._flush()
                    return
                if not isinstance(item, _Chunk):
                    try:
                        self._take(item)
                    except Exception:  # one run's failure stops nothing else
                        log.exception("live rules could not take %s", type(item).__name__)
            self._add_batch(chunks)
            if time.monotonic() >= next_tick:
                self._tick()
                next_tick = time.monotonic() + self.flush_s
            self.cpu_s = time.thread_time() - cpu_before

    def _add_batch(self, chunks: list[_Chunk]) -> None:
        """Chunks taken off the queue together, each run's in the order they came."""
        by_run: dict[str, list[_Chunk]] = {}
        for chunk in chunks:
            by_run.setdefault(chunk.run_id, []).append(chunk)
        for run_chunks in by_run.values():
            try:
                self._add(run_chunks)
            except Exception:  # one bad chunk or run stops nothing else
                log.exception("live rules could not evaluate the chunks of run %s", run_chunks[0].run_id)

    def _take(self, item: object) -> None:
        if isinstance(item, _Chunk):
            self._add([item])
        elif isinstance(item, _Started):
            self._gave_up.pop(item.run_id, None)
            self._keep(self._new_run(item.run_id, item.robot_id, changed=False))  # nothing in its file to read
        elif isinstance(item, _HandOver):
            run = self._runs.pop(item.run_id, None)
            if run is not None and not self._is_whole(run):
                run.whole = False
            self._gave_up.pop(item.run_id, None)
            with self._lock:
                self._overflowed.discard(item.run_id)
            item.answer.set_result(HandedOver(self._running.version, run))

    def _tick(self) -> None:
        try:
            self.reload_rules()
            self._flush()
        except Exception as exc:  # the catalog is down: the next tick writes what changed
            log.warning("live rules not written (%s: %s); retrying", type(exc).__name__, exc)

    def _add(self, chunks: list[_Chunk]) -> None:
        """Chunks of one run, in order, to its evaluator (those it was fed already skipped)."""
        first = chunks[0]
        if first.run_id in self._gave_up:
            return
        run = self._runs.get(first.run_id)
        if run is None:
            run = self._open(first)
        else:
            self._runs.move_to_end(first.run_id)
        fresh = []
        for chunk in chunks:
            if chunk.meta.chunk_id not in run.seen:  # (else read from its file when the evaluator started)
                run.seen.add(chunk.meta.chunk_id)
                fresh.append((chunk.msg, chunk.meta))
        if fresh:
            run.evaluator.add_many(fresh)
            self.evaluated_chunks += len(fresh)
            run.changed = True

    def _new_run(self, run_id: str, robot_id: str, *, changed: bool) -> HotRun:
        running = self._running
        evaluator = RunEvaluator(running.rules, max_events=self.max_events)
        return HotRun(run_id, robot_id, running.version, evaluator, changed=changed)

    def _keep(self, run: HotRun) -> None:
        self._runs[run.run_id] = run
        while len(self._runs) > self.max_runs:
            evicted, _ = self._runs.popitem(last=False)
            self._gave_up[evicted] = True  # evaluated from its data at sealing

    def _open(self, chunk: _Chunk) -> HotRun:
        """A new evaluator for a run whose start it did not see (after a restart, an eviction or a
        rules change), fed what the run's hot file holds so far."""
        run = self._new_run(chunk.run_id, chunk.robot_id, changed=True)
        recording = self.hot_runs.hot_recording(chunk.run_id) if self.hot_runs is not None else None
        if recording is None:
            run.whole = False
        else:
            indexed = open_hot(recording)
            try:
                for event in read_events(indexed, wanted_rows(indexed.index(), run.evaluator)):
                    if isinstance(event, ArrowMessage):
                        meta = chunk_meta(event)
                        run.seen.add(meta.chunk_id)
                        run.evaluator.add(event, meta)
            finally:
                indexed.close()
        self._keep(run)
        return run

    def _is_whole(self, run: HotRun) -> bool:
        with self._lock:
            overflowed = run.run_id in self._overflowed
        return run.whole and not overflowed and run.evaluator.in_order

    def reload_rules(self) -> None:
        """Follow the running rules (a new version resets the hot runs' evaluators)."""
        with session_scope(self.node.catalog) as session:
            current = current_rules(session)
            if (current.version if current is not None else NO_RULES_VERSION) == self._running.version:
                return
            running = running_rules(session)
        log.info("live rules: now version %d", running.version)
        self._running = running
        self._filter = _Filter(RunEvaluator(running.rules, max_events=self.max_events), {})
        self._runs.clear()  # each starts again from its file with its next chunk
        self._gave_up.clear()

    def _flush(self) -> None:
        """Write each changed run's events and metrics so far, all in one transaction (a commit is
        what a write costs most on an embedded catalog)."""
        due: list[HotRun] = []
        for run in (run for run in self._runs.values() if run.changed):
            run.events.extend(run.evaluator.take_closed())
            if run.events_written == len(run.events) and run.flushes_unwritten + 1 < METRICS_EVERY:
                run.flushes_unwritten += 1  # only metrics moved: written a few flushes on
                continue
            due.append(run)
        if not due:
            return
        now = self.node.clock()
        with session_scope(self.node.catalog, write=True) as session:
            rows = queries.get_runs(session, [run.run_id for run in due])  # one query for them all
            # (a run without its catalog row yet waits for the next tick; one sealed meanwhile is
            # evaluated at its next seal: the data that came after it)
            written = [run for run in due if run.run_id in rows]
            hot = [(run, rows[run.run_id]) for run in written if rows[run.run_id].tier == Tier.HOT]
            new = replace_evaluations(session, [_so_far(run, row) for run, row in hot], now)
            announce_events(session, new)
            pulls = self._queue_trigger_pulls(session, hot, new, now)
        trigger_pulls_made[DEPOT] += pulls
        for run in written:
            run.changed = False
            run.events_written, run.flushes_unwritten = len(run.events), 0

    def _queue_trigger_pulls(
        self, session: Session, hot: list[tuple[HotRun, Run]], new: list[Event], now: dt.datetime
    ) -> int:
        """A trigger pull for each new event a `[[trigger]]` of the running rules names."""
        running = self._running
        if not new or not running.rules.triggers:
            return 0
        by_run: dict[str, list[Event]] = {}
        for event in new:
            by_run.setdefault(event.run_id, []).append(event)
        pulls = 0
        for run, row in hot:
            if run.run_id in by_run and run.version == running.version:
                pulls += queue_trigger_pulls(session, row, by_run[run.run_id], running.rules.triggers, run.version, now)
        return pulls


def _so_far(run: HotRun, row: Run) -> EvaluationFacts:
    """A hot run's evaluation as it stands: its complete events and its metrics so far."""
    evaluator = run.evaluator
    metrics = evaluator.metrics_so_far(dict(properties_of(row)))
    evaluation = Evaluation(list(run.events), metrics, False, None, evaluator.in_order)
    return evaluation_facts(run.run_id, row.robot_id, run.version, LIVE, evaluation)
