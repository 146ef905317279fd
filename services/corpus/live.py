"""The rules, live: hot runs evaluated as their chunks arrive.

Ingest tells `LiveRules` (its `ChunkObserver`) of each new recording chunk an entity of which a rule
names; `chunk` puts it on a bounded queue and returns. One worker thread takes the chunks off and
keeps a `RunEvaluator` per hot run (at most `max_runs`, the least recently fed evicted); every
`flush_s` it writes each changed run's events and metrics so far (`state="live"`). Ingest never
waits: a full queue drops the chunk, and the run's live result no longer counts as whole (its
sealing evaluates the stored run).

A run's evaluator starts from the run's hot file as it stands (its wanted chunks read through the
chunk index), and afterwards skips the chunks it holds already: a run first seen after a restart,
an eviction or a rules change is still evaluated from its start. At sealing, `hand_over` gives the
run's evaluator to the sealing (through the queue, behind the run's last chunks), with the ids of
the chunks it was fed: it gives the final values only if those are every wanted chunk of the
sealed run.

The running rules are re-read from the catalog every `flush_s`; a new version resets the hot runs'
evaluators (each starts again from its file with its next chunk).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import OrderedDict
from concurrent.futures import Future
from dataclasses import dataclass, field

from cachetools import FIFOCache

from catalog import queries
from catalog.corpus import current_rules
from catalog.db import session_scope
from core.states import Tier
from services.corpus.evaluation import (
    LIVE,
    NO_RULES_VERSION,
    RunningRules,
    announce_events,
    properties_of,
    running_rules,
    wanted_rows,
    write_evaluation,
)
from services.hot.read import HotRuns
from services.node import Node
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.messages import ArrowMessage
from services.rules.evaluate import Evaluation, FoundEvent, RunEvaluator
from services.rules.spec import RuleSet
from services.runs.indexed import open_hot, read_events

log = logging.getLogger(__name__)

QUEUE_CHUNKS = 4096  # chunks waiting for the worker; past it they are dropped (the run is not whole)
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
        self._queue: queue.Queue[object] = queue.Queue(maxsize=queue_chunks)
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
        try:
            self._queue.put_nowait(_Chunk(run_id, robot_id, msg, meta))
        except queue.Full:
            with self._lock:
                self._overflowed.add(run_id)
                self.dropped_chunks += 1

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
        self._queue.put(_STOP)
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
        try:
            self._queue.put(_HandOver(run_id, answer), timeout=timeout_s)
            return answer.result(timeout_s)
        except (queue.Full, TimeoutError):
            log.warning("live rules did not hand run %s over in time: it is evaluated from its data", run_id)
            return None

    # --- the worker -------------------------------------------------------------------------

    def _work(self) -> None:
        next_tick = time.monotonic() + self.flush_s
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, next_tick - time.monotonic()))
            except queue.Empty:
                item = None
            if item is _STOP:
                self._flush()
                return
            try:
                self._take(item)
            except Exception:  # one bad chunk or run stops nothing else
                log.exception("live rules could not evaluate a chunk")
            if time.monotonic() >= next_tick:
                self._tick()
                next_tick = time.monotonic() + self.flush_s

    def _take(self, item: object) -> None:
        if isinstance(item, _Chunk):
            self._add(item)
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

    def _add(self, chunk: _Chunk) -> None:
        if chunk.run_id in self._gave_up:
            return
        run = self._runs.get(chunk.run_id)
        if run is None:
            run = self._open(chunk)
        else:
            self._runs.move_to_end(chunk.run_id)
        if chunk.meta.chunk_id in run.seen:
            return  # read from its file when the evaluator started
        run.seen.add(chunk.meta.chunk_id)
        run.evaluator.add(chunk.msg, chunk.meta)
        run.changed = True

    def _open(self, chunk: _Chunk) -> HotRun:
        """A new evaluator for the run, fed what its hot file holds so far."""
        running = self._running
        run = HotRun(
            chunk.run_id, chunk.robot_id, running.version, RunEvaluator(running.rules, max_events=self.max_events)
        )
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
        self._runs[chunk.run_id] = run
        while len(self._runs) > self.max_runs:
            evicted, _ = self._runs.popitem(last=False)
            self._gave_up[evicted] = True  # evaluated from its data at sealing
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
        """Write each changed run's events and metrics so far."""
        changed = [run for run in self._runs.values() if run.changed]
        for run in changed:
            run.events.extend(run.evaluator.take_closed())
            run.changed = False
            if not self._write(run):
                run.changed = True  # its catalog row is not there yet: the next tick

    def _write(self, run: HotRun) -> bool:
        now = self.node.clock()
        with session_scope(self.node.catalog, write=True) as session:
            row = queries.get_run(session, run.run_id)
            if row is None:
                return False
            if row.tier != Tier.HOT:
                return True  # data that came after the run was sealed: evaluated at its next seal
            evaluation = _so_far(run, properties_of(row))
            new = write_evaluation(session, run.run_id, row.robot_id, run.version, LIVE, evaluation, now, run.events)
            announce_events(session, new)
        return True


def _so_far(run: HotRun, properties: dict[str, dict[str, object]]) -> Evaluation:
    """A hot run's evaluation as it stands: its complete events and its metrics so far."""
    evaluator = run.evaluator
    metrics = evaluator.metrics_so_far(dict(properties))
    return Evaluation(list(run.events), metrics, False, None, evaluator.in_order)
