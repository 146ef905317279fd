"""A run's events and metrics under a rule set, chunk by chunk.

`RunEvaluator` is fed a run's recording chunks as they come (live: ingest's order) and reads only
those of entities the rules name (`wants`: one dict lookup once a path was seen) and robots' events
under `/events/**`. Within a chunk, samples are taken in the order of the rule's timeline. The
numeric conditions and path lengths need each entity's samples in time order across chunks: when
an entity's chunk starts before the last time seen for it, the live result is not exact and
`in_order` says so (the sealed run is then evaluated again from its data). `evaluate_messages`, for
a stored run, gathers those samples and sorts them before evaluating, so its result is exact
whatever the order of the chunks.

Events stop at `max_events` (FLEET_MAX_EVENTS_PER_RUN): the evaluation says so (`capped`) and names
the rules that found more. Metrics of events (`event_count`, `duration_s`) count every event found.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.rrd.chunk import ChunkMeta
from services.rrd.errors import InvalidChunkError
from services.rrd.messages import ArrowMessage
from services.rrd.validate import validated_batch
from services.rrd.values import (
    LEVEL,
    SCALARS,
    TEXT,
    TRANSLATION,
    data_columns,
    first_floats,
    first_texts,
    index_columns,
    vectors,
)
from services.rules.conditions import (
    Found,
    NumericCondition,
    label_of,
    robot_kind,
    robot_severity,
    text_matches,
)
from services.rules.metrics import EventTotals, PathLength, ScalarStats, property_value
from services.rules.spec import LOG_TIME, NUMERIC, SCALAR_METRICS, EventRule, RuleSet

log = logging.getLogger(__name__)

Index = dict[str, tuple[str, np.ndarray, np.ndarray]]  # timeline -> (type, values, which rows have one)
_NO_TIME = np.iinfo(np.int64).min


@dataclass(frozen=True)
class FoundEvent:
    kind: str
    severity: str  # info | warn | error
    timeline: str
    timeline_type: str  # timestamp (ns since epoch) | sequence | duration (ns)
    start: int
    end: int  # inclusive; = start for an instant
    origin: str  # rule | robot
    rule: str | None  # the rule's name (None: a robot's event)
    label: str


@dataclass(frozen=True)
class MetricValue:
    name: str
    value: float | None
    text_value: str | None


@dataclass(frozen=True)
class Evaluation:
    events: list[FoundEvent]
    metrics: list[MetricValue]
    capped: bool  # max_events reached: events past it were not kept
    note: str | None  # which rules found more than were kept
    in_order: bool  # False: an entity's chunks came out of time order, the events may be inexact


class _Ordered:
    """One entity's samples on one timeline for a consumer that needs them in time order: passed
    on chunk by chunk (live), or kept and passed on once, sorted, at the end (`buffered`)."""

    def __init__(self, feed: Any, buffered: bool) -> None:
        self.feed, self.buffered = feed, buffered
        self.pieces: list[tuple[np.ndarray, np.ndarray]] = []

    def add(self, times: np.ndarray, values: np.ndarray) -> Any:
        if not self.buffered:
            return self.feed(times, values)
        self.pieces.append((times, values))
        return []

    def flush(self) -> Any:
        if not self.pieces:
            return []
        times = np.concatenate([t for t, _ in self.pieces])
        values = np.concatenate([v for _, v in self.pieces])
        self.pieces = []
        order = np.argsort(times, kind="stable")
        return self.feed(times[order], values[order])


@dataclass
class _Condition:
    condition: NumericCondition
    samples: _Ordered
    entity: str


@dataclass
class _Read:
    """What the rules read of one chunk."""

    path: str
    kind: str | None  # robots' events kind of the entity (under /events/**)
    numeric: list[EventRule]
    texts: list[EventRule]
    scalar_stats: bool
    columns: dict[str, Any]
    index: Index
    values: np.ndarray | None  # the first instance of each row's Scalars, when read
    reads_text: bool
    reads_path: bool

    @property
    def scalars_only(self) -> bool:
        return self.values is not None and not self.reads_text and not self.reads_path

    def joins(self, other: _Read) -> bool:
        """Whether `other` can be evaluated in one with this read: the same entity's Scalars alone,
        on the same timelines."""
        return (
            self.scalars_only
            and other.scalars_only
            and other.path == self.path
            and {n: t for n, (t, _, _) in other.index.items()} == {n: t for n, (t, _, _) in self.index.items()}
        )


@dataclass
class _Totals:
    events: list[FoundEvent] = field(default_factory=list)
    dropped: dict[str, int] = field(default_factory=dict)  # rule (or robot kind) -> events not kept
    by_kind: EventTotals = field(default_factory=EventTotals)


class RunEvaluator:
    """One run's evaluation under `rules`, fed its recording chunks (`add`)."""

    def __init__(self, rules: RuleSet, *, max_events: int, buffered: bool = False) -> None:
        self.rules, self.max_events, self.buffered = rules, max_events, buffered
        self.in_order = True
        self._conditions: dict[tuple[str, str], _Condition] = {}  # (entity, rule name)
        self._paths: dict[str, tuple[PathLength, _Ordered]] = {}
        self._stats: dict[str, ScalarStats] = {}
        self._last_time: dict[tuple[str, str, str], int] = {}  # (entity, component, timeline) -> latest time
        self._found = _Totals()
        self._taken = 0

    def wants(self, entity_path: str) -> bool:
        """Whether a rule reads this entity, or it holds robots' events."""
        return self.rules.names_entity(entity_path) or robot_kind(entity_path) is not None

    def add(self, msg: ArrowMessage, meta: ChunkMeta) -> None:
        """Evaluate one chunk of the run's recording (a static chunk or one no rule reads: nothing)."""
        read = self._read(msg, meta)
        if read is not None:
            self._evaluate(read)

    def add_many(self, chunks: Iterable[tuple[ArrowMessage, ChunkMeta]]) -> None:
        """`add` each of `chunks`, in order, but the Scalars of consecutive chunks of one entity that
        only numeric rules and metrics read are evaluated together: a batch of one-row chunks costs
        one pass of the conditions, not one per chunk (the live worker's batches)."""
        group: list[_Read] = []
        for msg, meta in chunks:
            read = self._read(msg, meta)
            if read is None:
                continue
            if group and not group[-1].joins(read):
                self._evaluate_scalars(group)
                group = []
            if read.scalars_only:
                group.append(read)
            else:
                self._evaluate(read)
        if group:
            self._evaluate_scalars(group)

    def _read(self, msg: ArrowMessage, meta: ChunkMeta) -> _Read | None:
        """What the rules read of one chunk (None: nothing), its order on their timelines checked."""
        path = meta.entity_path
        if meta.is_static or not self.wants(path):
            return None
        rules, kind = self.rules.rules_for(path), robot_kind(path)
        names = meta.component_names
        numeric = [r for r in rules.events if r.when in NUMERIC]
        texts = [r for r in rules.events if r.when == "text"]
        reads_scalars = SCALARS in names and bool(numeric or rules.scalar_stats)
        reads_text = TEXT in names and bool(texts or kind)
        reads_path = TRANSLATION in names and rules.path_length
        if not (reads_scalars or reads_text or reads_path):
            return None
        try:
            batch = validated_batch(msg, meta)  # its values are read: never out of bounds
        except InvalidChunkError as exc:
            log.warning("rules skip %s", exc)  # ingest refuses such chunks; one stored before did not
            return None
        columns, index = data_columns(batch, meta), index_columns(batch, meta)
        if reads_scalars and numeric:
            self._check_order(path, SCALARS, {r.timeline for r in numeric}, meta)
        if reads_path:
            self._check_order(path, TRANSLATION, {LOG_TIME}, meta)
        values = first_floats(columns[SCALARS]) if reads_scalars else None
        return _Read(
            path, kind, numeric, texts, rules.scalar_stats, columns, index, values, reads_text, bool(reads_path)
        )

    def _evaluate(self, read: _Read) -> None:
        path, index, columns = read.path, read.index, read.columns
        if read.values is not None:
            self._numeric(path, read.numeric, read.values, index)
            if read.scalar_stats:
                self._scalar_stats(path, read.values, index)
        if read.reads_text:
            text, level = first_texts(columns[TEXT]), columns.get(LEVEL)
            levels: list[str | None] = first_texts(level) if level is not None else [None] * len(text)
            for rule in read.texts:
                self._text(rule, text, levels, index)
            if read.kind is not None:
                self._robot_events(read.kind, text, levels, index)
        if read.reads_path:
            self._path(path, columns[TRANSLATION], index)

    def _evaluate_scalars(self, group: list[_Read]) -> None:
        """Scalars-only reads of one entity, on the same timelines, evaluated as one."""
        if len(group) == 1:
            self._evaluate(group[0])
            return
        first = group[0]
        values = np.concatenate([r.values for r in group if r.values is not None])
        index: Index = {}
        for name, (kind, _, _) in first.index.items():
            times = np.concatenate([r.index[name][1] for r in group])
            has_time = np.concatenate([r.index[name][2] for r in group])
            index[name] = (kind, times, has_time)
        self._numeric(first.path, first.numeric, values, index)
        if first.scalar_stats:
            self._scalar_stats(first.path, values, index)

    def take_closed(self) -> list[FoundEvent]:
        """The events found since the last call whose range is complete (live use)."""
        events = self._found.events[self._taken :]
        self._taken = len(self._found.events)
        return events

    def metrics_so_far(self, properties: dict[str, dict[str, Any]]) -> list[MetricValue]:
        """The run's metrics as they stand (live use: `finish` gives the final ones)."""
        return self._metrics(properties)

    def finish(self, properties: dict[str, dict[str, Any]]) -> Evaluation:
        """The run's events (those taken already too) and metrics, once its last chunk was added.
        `properties`: the run's recording properties (`fleet` -> {field: value})."""
        for held in self._conditions.values():
            self._emit_all(held.condition, held.samples.flush())
            self._emit_all(held.condition, held.condition.finish())
        for _, samples in self._paths.values():
            samples.flush()
        found = self._found
        events = sorted(found.events, key=lambda e: (e.timeline, e.start, e.end, e.kind, e.label))
        note = None
        if found.dropped:
            lost = ", ".join(f"{n} of {who}" for who, n in sorted(found.dropped.items()))
            note = f"the run reached the cap of {self.max_events} events (FLEET_MAX_EVENTS_PER_RUN); not kept: {lost}"
        return Evaluation(events, self._metrics(properties), bool(found.dropped), note, self.in_order)

    # --- per chunk -------------------------------------------------------------------------------

    def _numeric(self, path: str, rules: list[EventRule], values: np.ndarray, index: Index) -> None:
        for rule in rules:
            if rule.timeline not in index:
                continue
            kind, times, has_time = index[rule.timeline]
            keep = has_time & ~np.isnan(values)
            ordered_times, ordered_values = _in_time_order(times[keep], values[keep])
            held = self._conditions.get((path, rule.name))
            if held is None:
                condition = NumericCondition(rule, path, kind)
                held = self._conditions[(path, rule.name)] = _Condition(
                    condition, _Ordered(condition.feed, self.buffered), path
                )
            self._emit_all(held.condition, held.samples.add(ordered_times, ordered_values))

    def _scalar_stats(self, path: str, values: np.ndarray, index: Index) -> None:
        keep = ~np.isnan(values)
        log_time = index.get(LOG_TIME)
        times = np.where(log_time[2], log_time[1], _NO_TIME)[keep] if log_time is not None else None
        self._stats.setdefault(path, ScalarStats()).feed(values[keep], times)

    def _text(self, rule: EventRule, texts: list[str | None], levels: list[str | None], index: Index) -> None:
        if rule.timeline not in index:
            return
        timeline_type, times, has_time = index[rule.timeline]
        rows = np.flatnonzero(has_time)
        for found in text_matches(rule, times[rows], [texts[i] for i in rows], [levels[i] for i in rows]):
            event = FoundEvent(
                rule.name, rule.severity, rule.timeline, timeline_type, *_range(found), "rule", rule.name, found.label
            )
            self._emit(event, f"rule {rule.name}")

    def _robot_events(self, kind: str, texts: list[str | None], levels: list[str | None], index: Index) -> None:
        if not index:
            return
        timeline = LOG_TIME if LOG_TIME in index else min(index)
        timeline_type, times, has_time = index[timeline]
        for row in np.flatnonzero(has_time).tolist():
            text = texts[row]
            if text is not None:
                t = int(times[row])
                event = FoundEvent(
                    kind, robot_severity(levels[row]), timeline, timeline_type, t, t, "robot", None, label_of(text)
                )
                self._emit(event, f"robot events {kind}")

    def _path(self, path: str, column: Any, index: Index) -> None:
        if LOG_TIME not in index:
            return
        _, times, has_time = index[LOG_TIME]
        points, has = vectors(column, 3, len(times))
        keep = has & has_time & np.isfinite(points).all(axis=1)
        ordered_times, ordered_points = _in_time_order(times[keep], points[keep])
        held = self._paths.get(path)
        if held is None:
            length = PathLength()
            held = self._paths[path] = (length, _Ordered(length.feed, self.buffered))
        held[1].add(ordered_times, ordered_points)

    def _check_order(self, path: str, component: str, timelines: set[str], meta: ChunkMeta) -> None:
        """Whether this chunk of an entity's `component` starts, on each of `timelines`, at or after
        the latest time seen of it (else the live result is not exact: `in_order`)."""
        for timeline in meta.timelines:
            if timeline.name not in timelines:
                continue
            key = (path, component, timeline.name)
            last = self._last_time.get(key)
            if last is not None and timeline.range.min < last and not self.buffered:
                self.in_order = False
            self._last_time[key] = timeline.range.max if last is None else max(last, timeline.range.max)

    # --- events and metrics ----------------------------------------------------------------------

    def _emit_all(self, condition: NumericCondition, found: list[Found]) -> None:
        rule = condition.rule
        for each in found:
            event = FoundEvent(
                rule.name,
                rule.severity,
                rule.timeline,
                condition.timeline_type,
                *_range(each),
                "rule",
                rule.name,
                each.label,
            )
            self._emit(event, f"rule {rule.name}")

    def _emit(self, event: FoundEvent, who: str) -> None:
        found = self._found
        found.by_kind.add(event.kind, event.timeline_type, event.start, event.end)
        if len(found.events) >= self.max_events:
            found.dropped[who] = found.dropped.get(who, 0) + 1
            return
        found.events.append(event)

    def _metrics(self, properties: dict[str, dict[str, Any]]) -> list[MetricValue]:
        out = []
        for metric in self.rules.metrics:
            value: float | None = None
            text: str | None = None
            if metric.kind == "path_length" and metric.entity in self._paths:
                value = self._paths[metric.entity][0].value()
            elif metric.kind in SCALAR_METRICS and metric.entity in self._stats:
                value = self._stats[metric.entity].value(metric.kind)
            elif metric.kind == "event_count" and metric.event is not None:
                value = self._found.by_kind.count(metric.event)
            elif metric.kind == "duration_s" and metric.event is not None:
                value = self._found.by_kind.duration_s(metric.event)
            elif metric.kind == "property" and metric.property is not None:
                value, text = property_value(properties, metric.property) or (None, None)
            if value is not None or text is not None:
                out.append(MetricValue(metric.name, value, text))
        return out


def evaluate_messages(
    rules: RuleSet,
    messages: Iterable[tuple[ArrowMessage, ChunkMeta]],
    properties: dict[str, dict[str, Any]],
    *,
    max_events: int,
) -> Evaluation:
    """A stored run's evaluation, exact whatever the order of its chunks (each entity's samples are
    sorted by time before the numeric conditions and path lengths read them)."""
    evaluator = RunEvaluator(rules, max_events=max_events, buffered=True)
    for msg, meta in messages:
        evaluator.add(msg, meta)
    return evaluator.finish(properties)


def _in_time_order(times: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if len(times) < 2 or bool((times[1:] >= times[:-1]).all()):
        return times, values
    order = np.argsort(times, kind="stable")
    return times[order], values[order]


def _range(found: Found) -> tuple[int, int]:
    return found.start, found.end
