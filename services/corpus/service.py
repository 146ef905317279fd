"""The corpus as people use it: the rules file applied (checked whole, each version kept with who
applied it and when), events found with filters and a cursor, people's annotations, and run tags.
Each function answers the JSON the REST API gives.

Events are listed newest first by when the depot recorded them (`created_at`), and `since`/`until`
filter on that time too: it is the one time every event has (a sequence timeline's events have no
time of day), and paging by it is stable while rules add events.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import sqlalchemy.exc as sa_exc
from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus
from catalog import edge as edge_db
from catalog.db import session_scope
from catalog.models import Event
from catalog.queries import require_run, run_timelines
from core.clock import iso_utc
from core.cursors import decode_cursor, encode_cursor
from core.errors import BadParameterError, ConflictError, InvalidRulesError, NotFoundError
from services.corpus.links import Viewer, event_answer
from services.rules.spec import RuleSet, parse_rules
from services.runs.download import parse_time_value

SEVERITIES = corpus.SEVERITIES
ORIGINS = (corpus.RULE, corpus.ROBOT, corpus.PERSON)
MAX_LIMIT = 1000
MAX_FILTER_VALUES = 32
PERSON_KIND = "annotation"  # a person's event when they name no kind
MAX_TAGS = 100  # in one request
_TAG = re.compile(r"[^\s,]{1,128}")

# Told of each new rules version once it is recorded (the live evaluator takes the new set).
RulesApplied = Callable[[RuleSet, int], None]


# --- rules ------------------------------------------------------------------------------------------


def apply_rules(
    catalog: sessionmaker[Session], text: str, who: str, now: dt.datetime, on_applied: RulesApplied | None = None
) -> dict[str, Any]:
    """Check `text` whole (InvalidRulesError naming every problem: nothing recorded, the running set
    untouched) and record it as a new version by `who`; the same text as the running set makes no
    version (`changed` false)."""
    rules = parse_rules(text)
    try:
        with session_scope(catalog, write=True) as session:
            version, changed = corpus.add_rules_version(session, text, who, now)
            answer = _version_answer(version, rules)
    except sa_exc.IntegrityError as exc:  # another apply took the same version number at the same moment
        raise ConflictError("another rules file was applied at the same moment: apply yours again") from exc
    if changed and on_applied is not None:
        on_applied(rules, answer["version"])
    return {**answer, "changed": changed}


def rules_answer(catalog: sessionmaker[Session], version: int | None = None) -> dict[str, Any]:
    """The running set (or an older `version`): its text, what it holds, who applied it and when.
    Before the first apply: the empty set, version None."""
    with session_scope(catalog) as session:
        found = corpus.current_rules(session) if version is None else corpus.rules_version(session, version)
        if found is None:
            if version is not None:
                raise NotFoundError(f"no rules version {version}: see GET /v1/rules/history or `fleet rules history`")
            return _version_answer(None, RuleSet.empty())
        try:
            rules = parse_rules(found.text)
        except InvalidRulesError as exc:  # held before the language changed: shown, not hidden
            return {**_version_answer(found, RuleSet.empty()), "problems": exc.problems}
        return _version_answer(found, rules)


def rules_history_answer(catalog: sessionmaker[Session]) -> dict[str, Any]:
    """Every version, newest first, with who applied it and when (the text: GET /v1/rules?version=N)."""
    with session_scope(catalog) as session:
        versions = corpus.rules_history(session)
        return {
            "versions": [
                {
                    "version": v.version,
                    "digest": v.digest,
                    "created_by": v.created_by,
                    "created_at": iso_utc(v.created_at),
                }
                for v in versions
            ]
        }


def _version_answer(version: Any, rules: RuleSet) -> dict[str, Any]:
    return {
        "version": version.version if version is not None else None,
        "text": version.text if version is not None else "",
        "digest": version.digest if version is not None else None,
        "created_by": version.created_by if version is not None else None,
        "created_at": iso_utc(version.created_at) if version is not None else None,
        "rules": rules_summary(rules),
    }


def rules_summary(rules: RuleSet) -> dict[str, Any]:
    """What a rule set holds, each rule's fields as written (its compiled forms left out)."""

    def plain(rule: Any) -> dict[str, Any]:
        return {f.name: getattr(rule, f.name) for f in dataclasses.fields(rule) if f.compare}

    return {
        "events": [plain(r) for r in rules.events],
        "metrics": [plain(r) for r in rules.metrics],
        "triggers": [plain(r) for r in rules.triggers],
    }


# --- events -----------------------------------------------------------------------------------------


@dataclass
class EventFilter:
    kind: list[str] = field(default_factory=list)
    robot: list[str] = field(default_factory=list)
    run: list[str] = field(default_factory=list)
    severity: list[str] = field(default_factory=list)
    origin: list[str] = field(default_factory=list)
    source: str | None = None
    since: dt.datetime | None = None  # recorded at or after
    until: dt.datetime | None = None  # recorded before
    pending: bool = False  # only events whose window is asked of the robot, not at the depot yet
    limit: int = 100
    cursor: str | None = None

    def query(self) -> corpus.EventQuery:
        """The catalog's query, every value checked first (422 naming the parameter)."""
        if not 1 <= self.limit <= MAX_LIMIT:
            raise BadParameterError("limit", f"{self.limit} is not between 1 and {MAX_LIMIT}")
        for name, values, allowed in (
            ("severity", self.severity, SEVERITIES),
            ("origin", self.origin, ORIGINS),
        ):
            for value in values:
                if value not in allowed:
                    raise BadParameterError(name, f"{value!r} is not one of {', '.join(allowed)}")
        for name, values in (("kind", self.kind), ("robot", self.robot), ("run", self.run)):
            if len(values) > MAX_FILTER_VALUES:
                raise BadParameterError(name, f"{len(values)} values: at most {MAX_FILTER_VALUES}")
            if any("\x00" in v for v in values):
                raise BadParameterError(name, "contains a NUL character")
        if self.source is not None and "\x00" in self.source:
            raise BadParameterError("source", "contains a NUL character")
        return corpus.EventQuery(
            kinds=self.kind,
            robots=self.robot,
            runs=self.run,
            severities=self.severity,
            origins=self.origin,
            source=self.source,
            since=self.since,
            until=self.until,
            after=decode_cursor(self.cursor) if self.cursor else None,
            pending=self.pending,
            limit=self.limit,
        )


def events_answer(catalog: sessionmaker[Session], viewer: Viewer, flt: EventFilter) -> dict[str, Any]:
    """A page of events, newest first, and `next_cursor` (None on the last page)."""
    query = flt.query()
    with session_scope(catalog) as session:
        found = corpus.find_events(session, query)
        events = _answers(session, found, viewer)
        last = (found[-1].created_at, found[-1].id) if len(found) == query.limit else None
    return {"events": events, "next_cursor": encode_cursor(*last) if last else None}


def run_events_answer(catalog: sessionmaker[Session], viewer: Viewer, run_id: str) -> dict[str, Any]:
    """Every event of a run, in timeline order (404 for an unknown run)."""
    with session_scope(catalog) as session:
        require_run(session, run_id)
        return {"run": run_id, "events": _answers(session, corpus.events_of_run(session, run_id), viewer)}


def one_event_answer(catalog: sessionmaker[Session], viewer: Viewer, event_id: str) -> dict[str, Any]:
    with session_scope(catalog) as session:
        found = corpus.get_event(session, event_id)
        if found is None:
            raise NotFoundError(f"no event {event_id!r}: list events with GET /v1/events or `fleet events ls`")
        return _answers(session, [found], viewer)[0]


def _answers(session: Session, events: Sequence[Event], viewer: Viewer) -> list[dict[str, Any]]:
    """Events as answers, each saying where its window's data is (its pulls read in one query)."""
    data = edge_db.events_data(session, [e.id for e in events])
    return [event_answer(e, viewer, data[e.id]) for e in events]


# --- a person's events --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Annotation:
    """A person's event as asked: times as written (ISO-8601 or ns on a timestamp timeline, integers
    on a sequence one, `12.5s` or ns on a duration one); `end` None: an instant."""

    timeline: str
    start: str | int
    end: str | int | None = None
    label: str = ""
    note: str = ""
    severity: str = "info"
    kind: str = PERSON_KIND


def annotate(
    catalog: sessionmaker[Session],
    viewer: Viewer,
    run_id: str,
    asked: Annotation,
    who: str,
    now: dt.datetime,
    new_id: str,
) -> dict[str, Any]:
    """Record a person's event on a run (404 for an unknown run, 422 for a timeline the run does not
    have, a time that is not one of its type, or an end before the start)."""
    _check_annotation(asked)
    with session_scope(catalog, write=True) as session:
        run = require_run(session, run_id)
        timeline_type = _timeline_type(session, run_id, asked.timeline)
        start = _time("start", timeline_type, asked.start)
        end = start if asked.end is None else _time("end", timeline_type, asked.end)
        if end < start:
            raise BadParameterError("end", f"{asked.end!r} is before the start {asked.start!r}")
        facts = corpus.EventFacts(
            kind=asked.kind,
            severity=asked.severity,
            timeline=asked.timeline,
            timeline_type=timeline_type,
            start=start,
            end=end,
            origin=corpus.PERSON,
            source=who,
            label=asked.label,
            note=asked.note,
        )
        return event_answer(corpus.add_event(session, run_id, run.robot_id, facts, now, new_id), viewer)


def _check_annotation(asked: Annotation) -> None:
    corpus.check_event_fields(asked.kind, asked.severity, asked.timeline, asked.label, asked.note)


def _timeline_type(session: Session, run_id: str, name: str) -> str:
    timelines = {t.name: t.type for t in run_timelines(session, run_id)}
    if name not in timelines:
        have = ", ".join(sorted(timelines)) or "none yet"
        raise BadParameterError("timeline", f"run {run_id!r} has no timeline {name[:100]!r} (it has: {have})")
    return timelines[name]


def _time(name: str, timeline_type: str, value: str | int) -> int:
    if isinstance(value, bool):
        raise BadParameterError(name, f"{value!r} is not a {timeline_type} value")
    return parse_time_value(name, timeline_type, str(value).strip())


# --- tags ---------------------------------------------------------------------------------------------


def checked_tags(tags: Sequence[str]) -> list[str]:
    """Tags as given, each 1 to 128 characters with no whitespace or comma (422 naming the first
    that is not)."""
    if not tags:
        raise BadParameterError("tags", "name at least one tag")
    if len(tags) > MAX_TAGS:
        raise BadParameterError("tags", f"{len(tags)} tags: at most {MAX_TAGS} at once")
    for tag in tags:
        if not (_TAG.fullmatch(tag) and tag.isprintable()):
            raise BadParameterError("tags", f"{tag!r}: a tag is 1 to 128 characters, with no whitespace or comma")
    return list(dict.fromkeys(tags))


def add_tags(
    catalog: sessionmaker[Session], run_id: str, tags: Sequence[str], who: str, now: dt.datetime
) -> dict[str, Any]:
    """Tag a run (a tag it has already keeps who added it first)."""
    wanted = checked_tags(tags)
    with session_scope(catalog, write=True) as session:
        require_run(session, run_id)
        added = corpus.add_tags(session, run_id, wanted, who, now)
        return {**_tags_answer(session, run_id), "added": added}


def remove_tags(catalog: sessionmaker[Session], run_id: str, tags: Sequence[str]) -> dict[str, Any]:
    """Untag a run (tags it does not have are left out of `removed`)."""
    wanted = checked_tags(tags)
    with session_scope(catalog, write=True) as session:
        require_run(session, run_id)
        removed = corpus.remove_tags(session, run_id, wanted)
        return {**_tags_answer(session, run_id), "removed": removed}


def _tags_answer(session: Session, run_id: str) -> dict[str, Any]:
    return {
        "run": run_id,
        "tags": [
            {"tag": t.tag, "added_by": t.added_by, "added_at": iso_utc(t.added_at)}
            for t in corpus.tags_of(session, run_id)
        ],
    }
