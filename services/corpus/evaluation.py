"""Evaluating a stored run against the rules: reading only the chunks of the entities they name
(and robots' `/events/**`), by ranged reads planned from the run's chunk index.

A hot run is read from its file through `chunks.idx`; a sealed one from its warm `recording.rrd`
through `chunks.parquet`, neighbouring wanted chunks fetched in one read and the others never. A
cold run (not restored) or a deleted one is not read: its evaluation says it was skipped.

The writing side is here too, shared by the live worker, sealing and the backfill: what an
`Evaluation` becomes in the catalog (`write_evaluation`), and the robot's tags from its `fleet`
property.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy.orm import Session

from catalog import corpus as corpus_db
from catalog import queries, webhooks
from catalog.db import session_scope
from catalog.models import Event, Run
from catalog.webhooks import EVENT_PREFIX
from core.clock import iso_utc
from core.errors import ConflictError, GoneError
from core.states import Tier
from services.facts.identity import IDENTITY_PROPERTY
from services.hot.read import HotRuns
from services.node import Node
from services.rrd.chunk import chunk_meta
from services.rrd.chunk_index import CHUNK, IndexRow
from services.rrd.messages import ArrowMessage
from services.rules.evaluate import Evaluation, FoundEvent, RunEvaluator
from services.rules.spec import RuleSet, parse_rules
from services.runs.indexed import IndexedRecording, open_hot, open_sealed_object, read_events
from services.sealed.read import locate_sealed

log = logging.getLogger(__name__)

LIVE, FINAL, SKIPPED = "live", "final", "skipped"  # run_evaluations.state
COLD_NOTE = "cold: restore it to evaluate"
NO_RULES_VERSION = 0  # before the first rules file: robots' own events are still found
TAGS_FIELD = "tags"  # of the `fleet` property: the robot's tags


@dataclass(frozen=True)
class RunningRules:
    """The rules the depot runs now, and their version (0 and no rules before the first apply)."""

    version: int
    rules: RuleSet


def running_rules(session: Session) -> RunningRules:
    current = corpus_db.current_rules(session)
    if current is None:
        return RunningRules(NO_RULES_VERSION, RuleSet.empty())
    return RunningRules(current.version, parse_rules(current.text))


@dataclass
class Reads:
    """What evaluating stored runs read: bytes and ranged reads; `pace` is told each read's size
    (the backfill's throttle)."""

    bytes_read: int = 0
    ranges: int = 0
    pace: Callable[[int], None] | None = None

    def counting(self, read: Callable[[int, int], bytes]) -> Callable[[int, int], bytes]:
        def counted(offset: int, length: int) -> bytes:
            data = read(offset, length)
            self.bytes_read += len(data)
            self.ranges += 1
            if self.pace is not None:
                self.pace(len(data))
            return data

        return counted


class NotReadable(Exception):
    """The run cannot be read here now (cold, deleted, or hot on another node); `note` says why."""

    def __init__(self, note: str, *, skipped: bool) -> None:
        super().__init__(note)
        self.note = note
        self.skipped = skipped  # recorded as skipped (cold); else simply left for later


def wanted_rows(rows: Iterable[IndexRow], evaluator: RunEvaluator) -> list[IndexRow]:
    """The recording chunks the rules read (in file order): no other chunk is fetched."""
    return [r for r in rows if r.kind == CHUNK and r.store_kind == "recording" and evaluator.wants(r.entity_path or "")]


def evaluate_recording(
    recording: IndexedRecording,
    rules: RuleSet,
    properties: Mapping[str, dict[str, Any]],
    *,
    max_events: int,
    reads: Reads | None = None,
) -> Evaluation:
    """The rules over a whole stored recording, reading only the chunks they want (each entity's
    samples sorted by time before they are judged: exact whatever the chunks' order)."""
    evaluator = RunEvaluator(rules, max_events=max_events, buffered=True)
    rows = wanted_rows(recording.index(), evaluator)
    counted = dataclasses.replace(recording, read=(reads or Reads()).counting(recording.read))
    for event in read_events(counted, rows):
        if isinstance(event, ArrowMessage):
            evaluator.add(event, recording.metas.get(event.offset) or chunk_meta(event))
    return evaluator.finish(dict(properties))


def open_run(node: Node, hot: HotRuns | None, run: Run, now: dt.datetime) -> IndexedRecording:
    """The run's recording for ranged reads, whichever tier holds it; NotReadable if it cannot be
    read here now. `close()` it when done."""
    if run.tier == Tier.HOT:
        recording = hot.hot_recording(run.id) if hot is not None else None
        if recording is None:
            raise NotReadable("hot on another node: evaluated when it is sealed", skipped=False)
        return open_hot(recording)
    try:
        sealed = locate_sealed(node.catalog, node.tiers.warm, run.id, now)
    except ConflictError:
        raise NotReadable(COLD_NOTE, skipped=True) from None
    except GoneError:
        raise NotReadable("deleted", skipped=True) from None
    rows = sealed.rows
    return open_sealed_object(sealed.store, sealed.key, sealed.size, lambda: rows)


def properties_of(run: Run) -> dict[str, dict[str, Any]]:
    loaded = json.loads(run.properties or "{}")
    return {str(k): dict(v) for k, v in loaded.items() if isinstance(v, dict)}


def robot_tags(properties: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The `tags` field of the `fleet` property: a list, or a comma-separated string."""
    given = properties.get(IDENTITY_PROPERTY, {}).get(TAGS_FIELD)
    if given is None:
        return []
    items = given.split(",") if isinstance(given, str) else given if isinstance(given, list) else [given]
    return sorted({str(item).strip() for item in items if str(item).strip()})


def event_facts(found: FoundEvent, version: int) -> corpus_db.EventFacts:
    source = "robot" if found.origin == corpus_db.ROBOT else f"rule {found.rule}@{version}"
    return corpus_db.EventFacts(
        kind=found.kind,
        severity=found.severity,
        timeline=found.timeline,
        timeline_type=found.timeline_type,
        start=found.start,
        end=found.end,
        origin=found.origin,
        source=source,
        label=found.label or "",
    )


def write_evaluation(
    session: Session,
    run_id: str,
    robot_id: str,
    version: int,
    state: str,
    evaluation: Evaluation,
    now: dt.datetime,
) -> list[Event]:
    """Replace the run's rule- and robot-made events and metrics with `evaluation`'s. Returns the
    new ones."""
    return corpus_db.replace_evaluations(session, [evaluation_facts(run_id, robot_id, version, state, evaluation)], now)


def evaluation_facts(
    run_id: str,
    robot_id: str,
    version: int,
    state: str,
    evaluation: Evaluation,
    events: Iterable[FoundEvent] | None = None,
) -> corpus_db.EvaluationFacts:
    """What the catalog keeps of `evaluation` (`events`: the events to write instead of its own, for
    a live run's events so far)."""
    return corpus_db.EvaluationFacts(
        run_id=run_id,
        robot_id=robot_id,
        rules_version=version,
        state=state,
        events=[event_facts(e, version) for e in (evaluation.events if events is None else events)],
        metrics=[corpus_db.MetricFacts(m.name, m.value, m.text_value) for m in evaluation.metrics],
        capped=evaluation.capped,
        note=evaluation.note,
    )


def evaluate_run(
    node: Node,
    hot: HotRuns | None,
    run_id: str,
    running: RunningRules,
    *,
    max_events: int,
    reads: Reads | None = None,
) -> tuple[Run, Evaluation]:
    """The running rules over a stored run (NotReadable when it cannot be read here now)."""
    with session_scope(node.catalog) as session:
        run = queries.require_run(session, run_id)
        session.expunge(run)
    recording = open_run(node, hot, run, node.clock())
    try:
        evaluation = evaluate_recording(
            recording, running.rules, properties_of(run), max_events=max_events, reads=reads
        )
    finally:
        recording.close()
    return run, evaluation


def announce_events(session: Session, new_events: Sequence[Event]) -> None:
    """Webhooks told of each new event (`event:KIND`), in the writer's transaction: at most once
    each, as an event found again (live, sealed, after a rules change) keeps its id."""
    if not new_events:
        return
    hooks = webhooks.webhooks(session)  # read once for all of them: a live flush may bring many
    if not hooks:
        return
    for event in new_events:
        webhooks.enqueue(session, EVENT_PREFIX + event.kind, event.id, event_payload(event), hooks=hooks)


def event_payload(event: Event) -> dict[str, Any]:
    return {
        "event_id": event.id,
        "run_id": event.run_id,
        "robot_id": event.robot_id,
        "kind": event.kind,
        "severity": event.severity,
        "timeline": event.timeline,
        "start": event.range_start,
        "end": event.range_end,
        "source": event.source,
        "label": event.label,
        "created_at": iso_utc(event.created_at),
    }
