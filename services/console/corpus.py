"""What the console reads and changes of the corpus (a run's events, metrics and tags; events
fleet-wide; people's tags and annotations), in one place: the pages call these functions, which
call the same service functions the REST API answers with. Events are handed on as the API answers
them (dicts), so a page shows what `GET /v1/events` says."""

from __future__ import annotations

import datetime as dt
import secrets
from dataclasses import dataclass, field
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus
from catalog.db import session_scope
from catalog.models import Event
from catalog.queries import require_run
from core.clock import iso_utc
from core.errors import BadParameterError
from core.timefmt import timestamp
from services.runs.download import parse_time_value

PAD_NS = 5_000_000_000  # a few seconds around an event on timestamp and duration timelines
SEVERITIES = ("info", "warn", "error")
MAX_TAG_LENGTH = 256
MAX_LABEL_LENGTH = 4096


@dataclass(frozen=True)
class RunCorpus:
    """A run's events (oldest first), metrics and tags."""

    events: list[dict[str, Any]] = field(default_factory=list)
    metrics: list[dict[str, Any]] = field(default_factory=list)
    tags: list[dict[str, Any]] = field(default_factory=list)


@dataclass(frozen=True)
class EventsAsked:
    """The events page's filters (empty: any) and its page."""

    kind: str = ""
    robot: str = ""
    severity: str = ""
    source: str = ""
    run: str = ""
    cursor: str = ""
    limit: int = 50


def padded(timeline_type: str, start: int, end: int) -> tuple[int, int]:
    """An event's window as its viewer link shows it: a few seconds either side on time timelines;
    a sequence's range as it is."""
    pad = 0 if timeline_type == "sequence" else PAD_NS
    return max(-(2**63), start - pad), min(2**63 - 1, end + pad)


def event_answer(event: Event) -> dict[str, Any]:
    on_clock = event.timeline_type == "timestamp"
    return {
        "id": event.id,
        "run_id": event.run_id,
        "robot_id": event.robot_id,
        "kind": event.kind,
        "severity": event.severity,
        "timeline": event.timeline,
        "timeline_type": event.timeline_type,
        "start": event.range_start,
        "end": event.range_end,
        "start_iso": timestamp(event.range_start) if on_clock else None,
        "end_iso": timestamp(event.range_end) if on_clock else None,
        "source": event.source,
        "origin": event.origin,
        "rules_version": event.rules_version,
        "label": event.label,
        "note": event.note,
        "created_at": iso_utc(event.created_at),
    }


def run_corpus(catalog: sessionmaker[Session], run_id: str) -> RunCorpus:
    with session_scope(catalog) as session:
        return RunCorpus(
            events=[event_answer(e) for e in corpus.events_of_run(session, run_id)],
            metrics=[
                {"name": m.name, "value": m.value, "text_value": m.text_value, "rules_version": m.rules_version}
                for m in corpus.metrics_of(session, run_id)
            ],
            tags=[
                {"tag": t.tag, "added_by": t.added_by, "added_at": iso_utc(t.added_at)}
                for t in corpus.tags_of(session, run_id)
            ],
        )


def events_page(catalog: sessionmaker[Session], asked: EventsAsked) -> tuple[list[dict[str, Any]], str | None]:
    """A page of events fleet-wide, newest first, and the next page's cursor (None at the end)."""
    if asked.severity and asked.severity not in SEVERITIES:
        raise BadParameterError("severity", f"{asked.severity!r} is not one of {', '.join(SEVERITIES)}")
    after = _cursor(asked.cursor) if asked.cursor else None
    with session_scope(catalog) as session:
        rows = _find_events(session, asked, after)
    found = [event_answer(e) for e in rows[: asked.limit]]
    more = len(rows) > asked.limit
    return found, (f"{rows[asked.limit - 1].created_at.isoformat()}|{rows[asked.limit - 1].id}" if more else None)


def _cursor(text: str) -> tuple[dt.datetime, str]:
    at, _, ident = text.partition("|")
    try:
        moment = dt.datetime.fromisoformat(at)
    except ValueError:
        raise BadParameterError("cursor", "not a cursor this page gave: start from the first page") from None
    return (moment if moment.tzinfo else moment.replace(tzinfo=dt.UTC)), ident


def _find_events(session: Session, asked: EventsAsked, after: tuple[dt.datetime, str] | None) -> list[Event]:
    select = sa.select(Event)
    for column, value in (
        (Event.kind, asked.kind),
        (Event.robot_id, asked.robot),
        (Event.severity, asked.severity),
        (Event.source, asked.source),
        (Event.run_id, asked.run),
    ):
        if value:
            select = select.where(column == value)
    if after is not None:
        select = select.where(
            sa.or_(Event.created_at < after[0], sa.and_(Event.created_at == after[0], Event.id < after[1]))
        )
    select = select.order_by(Event.created_at.desc(), Event.id.desc()).limit(asked.limit + 1)
    return list(session.scalars(select))


# --- people's changes -------------------------------------------------------------------------------


def check_tags(tags: list[str]) -> list[str]:
    if not tags:
        raise BadParameterError("tag", "give at least one tag")
    for tag in tags:
        if len(tag) > MAX_TAG_LENGTH or any(ch.isspace() or ch == "\x00" for ch in tag):
            raise BadParameterError("tag", f"{tag[:40]!r}: a tag is up to {MAX_TAG_LENGTH} characters, no spaces")
    return tags


def add_tags(catalog: sessionmaker[Session], run_id: str, tags: list[str], who: str, now: dt.datetime) -> list[str]:
    check_tags(tags)
    with session_scope(catalog) as session:
        require_run(session, run_id)
        return corpus.add_tags(session, run_id, tags, who, now)


def remove_tags(catalog: sessionmaker[Session], run_id: str, tags: list[str]) -> list[str]:
    check_tags(tags)
    with session_scope(catalog) as session:
        require_run(session, run_id)
        return corpus.remove_tags(session, run_id, tags)


@dataclass(frozen=True)
class Annotation:
    timeline: str
    start: str
    end: str
    label: str
    kind: str = "annotation"
    severity: str = "info"


def annotate(
    catalog: sessionmaker[Session],
    run: dict[str, Any],
    asked: Annotation,
    who: str,
    now: dt.datetime,
) -> dict[str, Any]:
    """A person's event on the run (`run`: its answer, for its robot and timelines)."""
    types = {t["name"]: t["type"] for t in run["timelines"]}
    if asked.timeline not in types:
        raise BadParameterError(
            "timeline", f"{asked.timeline!r} is not a timeline of this run: {', '.join(sorted(types)) or 'none'}"
        )
    kind = types[asked.timeline]
    if not asked.start.strip():
        raise BadParameterError("start", "give the annotation's start (and its end, or none for an instant)")
    start = parse_time_value("start", kind, asked.start.strip())
    end = parse_time_value("end", kind, asked.end.strip()) if asked.end.strip() else start
    if end < start:
        raise BadParameterError("end", f"end {asked.end!r} is before start {asked.start!r}")
    if len(asked.label) > MAX_LABEL_LENGTH:
        raise BadParameterError("label", f"a label is up to {MAX_LABEL_LENGTH} characters")
    if asked.severity not in SEVERITIES:
        raise BadParameterError("severity", f"{asked.severity!r} is not one of {', '.join(SEVERITIES)}")
    facts = corpus.EventFacts(
        kind=asked.kind or "annotation",
        severity=asked.severity,
        timeline=asked.timeline,
        timeline_type=kind,
        start=start,
        end=end,
        origin=corpus.PERSON,
        source=who,
        label=asked.label,
    )
    with session_scope(catalog) as session:
        row = corpus.add_event(session, run["id"], run["robot_id"], facts, now, "ev-" + secrets.token_hex(8))
        return event_answer(row)
