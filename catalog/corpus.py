"""Catalog reads and writes of the corpus: versions of the rules file, what rules made of each run
(its events and metrics, and which version made them), people's annotations, and tags.

A run's evaluation is replaced whole in one transaction (`replace_evaluation`): its rule- and
robot-made events and its metrics go, the new ones come, so re-evaluating never doubles anything;
people's events and tags are not touched, nor are the events a robot's agent reported when it fired
a trigger (origin rule, source robot: its rules found them on the robot, and their window may be on
its way) unless the depot's own evaluation finds them too. Event ids are derived from what the event is (run, origin,
kind, timeline, start, entity), so the same event found again (live, then sealed, then after a rules
change) keeps its id: what was told of it once (webhooks) is not told again.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog import dataset_columns as columns
from catalog import lakehouse
from catalog.edge import AWAITED_STATES
from catalog.models import Event, Pull, RulesVersion, RunEvaluation, RunMetric, RunTag
from core.errors import BadParameterError
from core.states import PullState
from core.text import storable

RULE, ROBOT, PERSON = "rule", "robot", "person"  # an event's origin
MADE_BY_EVALUATION = (RULE, ROBOT)  # the origins a re-evaluation replaces
REPORTED_BY_ROBOT = "robot"  # the source of a rule's event a robot's agent reported (origin rule)
ROBOT_TAGGER = "robot"  # added_by of the tags a robot's `fleet` property gives

# What an event may hold, checked the same wherever one comes from (a person, a robot's agent).
SEVERITIES = ("info", "warn", "error")
TIMELINE_TYPES = ("timestamp", "sequence", "duration")
MAX_LABEL, MAX_NOTE = 1000, 10_000
_KIND = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.:/-]{0,127}")
_TIMELINE_CHARS = 256  # events.timeline


def check_event_fields(kind: str, severity: str, timeline: str, label: str = "", note: str = "") -> None:
    """An event's kind, severity, timeline name, label and note as the catalog takes them (422
    naming the first field that is not)."""
    if severity not in SEVERITIES:
        raise BadParameterError("severity", f"{severity!r} is not one of {', '.join(SEVERITIES)}")
    if not _KIND.fullmatch(kind):
        raise BadParameterError("kind", f"{kind[:200]!r}: letters, digits and _ . : / -, 1 to 128 characters")
    if len(label) > MAX_LABEL:
        raise BadParameterError("label", f"{len(label)} characters: at most {MAX_LABEL}")
    if len(note) > MAX_NOTE:
        raise BadParameterError("note", f"{len(note)} characters: at most {MAX_NOTE}")
    if not timeline or "\x00" in timeline or len(timeline) > _TIMELINE_CHARS:
        raise BadParameterError("timeline", f"name one of the run's timelines (1 to {_TIMELINE_CHARS} characters)")
    for name, text in (("timeline", timeline), ("label", label), ("note", note)):
        if not storable(text):
            raise BadParameterError(name, "holds a NUL character or an unpaired surrogate: send plain UTF-8 text")


# --- the rules file's versions --------------------------------------------------------------------


def current_rules(session: Session) -> RulesVersion | None:
    """The running rules: the highest version (None before the first `fleet rules apply`)."""
    return session.scalars(sa.select(RulesVersion).order_by(RulesVersion.version.desc()).limit(1)).first()


def add_rules_version(session: Session, text: str, who: str, now: dt.datetime) -> tuple[RulesVersion, bool]:
    """A new version holding `text`, or the current one if it holds the same text already (applying
    a file twice makes no version and re-evaluates nothing). The flag says whether it is new."""
    digest = hashlib.sha256(text.encode()).hexdigest()
    current = current_rules(session)
    if current is not None and current.digest == digest:
        return current, False
    version = RulesVersion(
        version=(current.version + 1) if current is not None else 1,
        text=text,
        digest=digest,
        created_by=who,
        created_at=now,
    )
    session.add(version)
    session.flush()
    return version, True


def rules_history(session: Session) -> list[RulesVersion]:
    """Every version, newest first."""
    return list(session.scalars(sa.select(RulesVersion).order_by(RulesVersion.version.desc())))


def rules_version(session: Session, version: int) -> RulesVersion | None:
    return session.get(RulesVersion, version)


# --- what rules made of a run ---------------------------------------------------------------------


@dataclass(frozen=True)
class EventFacts:
    """An event as an evaluation or a person gives it, before it has an id and a row."""

    kind: str
    severity: str
    timeline: str
    timeline_type: str
    start: int
    end: int
    origin: str  # rule | robot | person
    source: str  # "rule NAME@V", "robot", or a token's subject
    label: str = ""
    note: str = ""
    entity: str = ""  # the entity it was found on (part of its identity, not stored)


@dataclass(frozen=True)
class MetricFacts:
    name: str
    value: float | None
    text_value: str | None


def event_id(run_id: str, facts: EventFacts) -> str:
    """The id of an evaluation's event: the same event found again keeps it."""
    key = "\x1f".join((run_id, facts.origin, facts.kind, facts.timeline, str(facts.start), facts.entity))
    return "ev-" + hashlib.sha256(key.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class EvaluationFacts:
    """One run's evaluation as `replace_evaluations` writes it."""

    run_id: str
    robot_id: str
    rules_version: int
    state: str
    events: Sequence[EventFacts]
    metrics: Sequence[MetricFacts]
    capped: bool
    note: str | None


def replace_evaluation(
    session: Session,
    *,
    run_id: str,
    robot_id: str,
    rules_version: int,
    state: str,
    events: Sequence[EventFacts],
    metrics: Sequence[MetricFacts],
    capped: bool,
    note: str | None,
    now: dt.datetime,
) -> list[Event]:
    """One run's `replace_evaluations`."""
    facts = EvaluationFacts(run_id, robot_id, rules_version, state, events, metrics, capped, note)
    return replace_evaluations(session, [facts], now)


def replace_evaluations(session: Session, evaluations: Sequence[EvaluationFacts], now: dt.datetime) -> list[Event]:
    """Replace each run's rule- and robot-made events, its metrics and its evaluation row. Returns
    the events that are new (not held before under the same id), and those a robot's agent reported
    that the depot finds now for the first time: what webhooks are told of.

    Only what differs is written (a live run is written every few seconds with mostly the same
    values): an event held before keeps its row and when it was first recorded. An event a robot's
    agent reported stays when this evaluation does not find it; when it does, it becomes the
    evaluation's (its source the rule's). What the runs hold is read in one query per table for
    all of them (the live rules write every hot run that changed at once)."""
    run_ids = [facts.run_id for facts in evaluations]
    if len(set(run_ids)) != len(run_ids):
        raise ValueError("one evaluation per run")
    held_events: dict[str, dict[str, Event]] = {run_id: {} for run_id in run_ids}
    for event in session.scalars(
        sa.select(Event).where(Event.run_id.in_(run_ids), Event.origin.in_(MADE_BY_EVALUATION))
    ):
        held_events[event.run_id][event.id] = event
    held_metrics: dict[str, dict[str, RunMetric]] = {run_id: {} for run_id in run_ids}
    for metric in session.scalars(sa.select(RunMetric).where(RunMetric.run_id.in_(run_ids))):
        held_metrics[metric.run_id][metric.name] = metric
    rows = session.scalars(sa.select(RunEvaluation).where(RunEvaluation.run_id.in_(run_ids)))
    held_evaluations = {row.run_id: row for row in rows}
    new: list[Event] = []
    for facts in evaluations:
        new += _replace_events(session, facts, held_events[facts.run_id], now)
        _replace_metrics(session, facts, held_metrics[facts.run_id], now)
        evaluation = held_evaluations.get(facts.run_id)
        if evaluation is None:
            evaluation = RunEvaluation(run_id=facts.run_id)
            session.add(evaluation)
        evaluation.rules_version = facts.rules_version
        evaluation.state = facts.state
        evaluation.events_capped = facts.capped
        evaluation.note = facts.note
        evaluation.evaluated_at = now
    lakehouse.queue_sealed(session, run_ids)
    session.flush()
    return new


def _replace_events(session: Session, facts: EvaluationFacts, held: dict[str, Event], now: dt.datetime) -> list[Event]:
    reported = {ident for ident, e in held.items() if _robot_reported(e)}
    rows: dict[str, Event] = {}
    for event in facts.events:
        row = _event_row(event_id(facts.run_id, event), facts.run_id, facts.robot_id, event, facts.rules_version, now)
        rows.setdefault(row.id, row)  # two identical findings are one event
    new: list[Event] = []
    for ident, row in rows.items():
        before = held.pop(ident, None)
        if before is None:
            session.add(row)
            new.append(row)
        else:
            _update(before, row, _EVENT_FACTS)
            if ident in reported and not _robot_reported(before):  # told of once the depot finds it too
                new.append(before)
    for ident, gone in held.items():
        if ident not in reported:
            session.delete(gone)
    return new


def _robot_reported(event: Event) -> bool:
    return event.origin == RULE and event.source == REPORTED_BY_ROBOT


_EVENT_FACTS = (
    "robot_id",
    "kind",
    "severity",
    "timeline",
    "timeline_type",
    "range_start",
    "range_end",
    "origin",
    "source",
    "rules_version",
    "label",
    "note",
)


def _update(held: object, fresh: object, fields: Sequence[str]) -> bool:
    """Copy onto `held` the `fields` of `fresh` that differ; whether any did."""
    changed = False
    for name in fields:
        value = getattr(fresh, name)
        if getattr(held, name) != value:
            setattr(held, name, value)
            changed = True
    return changed


def _replace_metrics(session: Session, facts: EvaluationFacts, held: dict[str, RunMetric], now: dt.datetime) -> None:
    columns.recount_metrics(
        session,
        facts.run_id,
        columns.metric_items((m.name, m.text_value) for m in held.values()),
        columns.metric_items((m.name, m.text_value) for m in facts.metrics),
    )
    for m in facts.metrics:
        fresh = RunMetric(
            run_id=facts.run_id,
            name=m.name,
            robot_id=facts.robot_id,
            value=m.value,
            text_value=m.text_value,
            rules_version=facts.rules_version,
            computed_at=now,
        )
        before = held.pop(m.name, None)
        if before is None:
            session.add(fresh)
        elif _update(before, fresh, ("robot_id", "value", "text_value", "rules_version")):
            before.computed_at = now
    for gone in held.values():
        session.delete(gone)


def set_evaluation_state(
    session: Session, run_id: str, rules_version: int, state: str, note: str | None, now: dt.datetime
) -> None:
    """Record that the run was looked at without new values (skipped: a cold run is not read)."""
    evaluation = session.get(RunEvaluation, run_id)
    if evaluation is None:
        session.add(
            RunEvaluation(
                run_id=run_id,
                rules_version=rules_version,
                state=state,
                events_capped=False,
                note=note,
                evaluated_at=now,
            )
        )
        return
    evaluation.rules_version, evaluation.state, evaluation.note, evaluation.evaluated_at = (
        rules_version,
        state,
        note,
        now,
    )


def evaluation_of(session: Session, run_id: str) -> RunEvaluation | None:
    return session.get(RunEvaluation, run_id)


def add_event(
    session: Session,
    run_id: str,
    robot_id: str,
    facts: EventFacts,
    now: dt.datetime,
    new_id: str,
    rules_version: int | None = None,
) -> Event:
    """A person's event (an annotation: `new_id` is fresh, since two people may mark the same span),
    or one a robot's agent reported (its id `event_id` of its facts, with the rules version that
    found it)."""
    row = _event_row(new_id, run_id, robot_id, facts, rules_version, now)
    session.add(row)
    lakehouse.queue_sealed(session, [run_id])
    session.flush()
    return row


def _event_row(
    ident: str, run_id: str, robot_id: str, facts: EventFacts, rules_version: int | None, now: dt.datetime
) -> Event:
    return Event(
        id=ident,
        run_id=run_id,
        robot_id=robot_id,
        kind=facts.kind,
        severity=facts.severity,
        timeline=facts.timeline,
        timeline_type=facts.timeline_type,
        range_start=facts.start,
        range_end=facts.end,
        origin=facts.origin,
        source=facts.source,
        rules_version=rules_version,
        label=facts.label,
        note=facts.note,
        created_at=now,
    )


def metrics_of(session: Session, run_id: str) -> list[RunMetric]:
    return list(session.scalars(sa.select(RunMetric).where(RunMetric.run_id == run_id).order_by(RunMetric.name)))


def event_counts_of(session: Session, run_id: str) -> dict[str, int]:
    """The run's events by kind."""
    rows = session.execute(
        sa.select(Event.kind, sa.func.count()).where(Event.run_id == run_id).group_by(Event.kind).order_by(Event.kind)
    )
    return {kind: int(count) for kind, count in rows}


def events_of_run(session: Session, run_id: str) -> list[Event]:
    return list(session.scalars(sa.select(Event).where(Event.run_id == run_id).order_by(Event.range_start, Event.id)))


def forget_run(session: Session, run_id: str) -> None:
    """A deleted run's events, metrics, tags and evaluation go with it."""
    for model in (Event, RunMetric, RunTag, RunEvaluation):
        session.execute(sa.delete(model).where(model.run_id == run_id))


# --- tags -----------------------------------------------------------------------------------------


def tags_of(session: Session, run_id: str) -> list[RunTag]:
    return list(session.scalars(sa.select(RunTag).where(RunTag.run_id == run_id).order_by(RunTag.tag)))


def add_tags(session: Session, run_id: str, tags: Iterable[str], who: str, now: dt.datetime) -> list[str]:
    """Add the tags the run does not have yet (who added a tag first is kept). Returns those added."""
    held = {t.tag for t in tags_of(session, run_id)}
    added = [tag for tag in dict.fromkeys(tags) if tag not in held]
    session.add_all(RunTag(run_id=run_id, tag=tag, added_by=who, added_at=now) for tag in added)
    if added:
        lakehouse.queue_sealed(session, [run_id])
    session.flush()
    return added


def remove_tags(session: Session, run_id: str, tags: Iterable[str]) -> list[str]:
    """Remove the given tags the run has. Returns those removed."""
    wanted = set(tags)
    held = [t for t in tags_of(session, run_id) if t.tag in wanted]
    for tag in held:
        session.delete(tag)
    if held:
        lakehouse.queue_sealed(session, [run_id])
    session.flush()
    return [t.tag for t in held]


def sync_robot_tags(session: Session, run_id: str, tags: Iterable[str], now: dt.datetime) -> None:
    """Make the run's robot-given tags these (a tag a person also gave stays theirs)."""
    wanted = set(tags)
    for held in tags_of(session, run_id):
        if held.added_by == ROBOT_TAGGER and held.tag not in wanted:
            session.delete(held)
            lakehouse.queue_sealed(session, [run_id])
    add_tags(session, run_id, sorted(wanted), ROBOT_TAGGER, now)


# --- events found -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class EventQuery:
    """Which events, newest first (by when the depot recorded them, then id). Empty lists: any."""

    kinds: Sequence[str] = ()
    robots: Sequence[str] = ()
    runs: Sequence[str] = ()
    severities: Sequence[str] = ()
    origins: Sequence[str] = ()
    source: str | None = None
    since: dt.datetime | None = None  # created at or after
    until: dt.datetime | None = None  # created before
    after: tuple[dt.datetime, str] | None = None  # the last (created_at, id) of the previous page
    pending: bool = False  # only events whose window is asked of the robot and not at the depot yet
    limit: int = 100


def find_events(session: Session, query: EventQuery) -> list[Event]:
    """A page of events (at most `query.limit`), newest first."""
    select = sa.select(Event)
    for column, values in (
        (Event.kind, query.kinds),
        (Event.robot_id, query.robots),
        (Event.run_id, query.runs),
        (Event.severity, query.severities),
        (Event.origin, query.origins),
    ):
        if values:
            select = select.where(column.in_(list(values)))
    if query.source is not None:
        select = select.where(Event.source == query.source)
    if query.since is not None:
        select = select.where(Event.created_at >= query.since)
    if query.until is not None:
        select = select.where(Event.created_at < query.until)
    if query.pending:
        awaited = sa.exists().where(Pull.event_id == Event.id, Pull.state.in_(AWAITED_STATES))
        done = sa.exists().where(Pull.event_id == Event.id, Pull.state == PullState.DONE)
        select = select.where(awaited, ~done)
    if query.after is not None:
        created, ident = query.after
        select = select.where(
            sa.or_(Event.created_at < created, sa.and_(Event.created_at == created, Event.id < ident))
        )
    select = select.order_by(Event.created_at.desc(), Event.id.desc()).limit(query.limit)
    return list(session.scalars(select))


def get_event(session: Session, ident: str) -> Event | None:
    return session.get(Event, ident)
