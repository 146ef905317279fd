"""What the console reads and changes of the corpus (a run's events, metrics and tags; events
fleet-wide; people's tags and annotations), in one place: the pages call these functions, which
call the corpus service the REST API answers with, so a page shows what `GET /v1/events` says and
an edit is checked as the API checks it."""

from __future__ import annotations

import datetime as dt
import secrets
from dataclasses import dataclass, field
from typing import Any

from fastapi import Request

from catalog import corpus
from catalog.db import session_scope
from core.errors import NotFoundError
from services.auth.scopes import Principal
from services.corpus import service
from services.corpus.links import Viewer, padded
from services.runs.links import lifetime, request_base

SEVERITIES = service.SEVERITIES
PAGE = 50  # events on a page of the Events page

__all__ = ["PAGE", "SEVERITIES", "EventsAsked", "RunCorpus", "padded"]


@dataclass(frozen=True)
class RunCorpus:
    """A run's events (in timeline order, as the API answers them), metrics and tags."""

    events: list[dict[str, Any]] = field(default_factory=list)
    metrics: list[dict[str, Any]] = field(default_factory=list)
    tags: list[dict[str, Any]] = field(default_factory=list)


@dataclass(frozen=True)
class EventsAsked:
    """The Events page's filters (empty: any) and its page."""

    kind: str = ""
    robot: str = ""
    severity: str = ""
    source: str = ""
    run: str = ""
    cursor: str = ""


def viewer(request: Request, principal: Principal) -> Viewer:
    """How event answers link to the viewer (as `GET /v1/events` makes them for this principal)."""
    state = request.app.state
    return Viewer(state.auth, principal, request_base(request), lifetime(None, state.settings.link_ttl_s))


def run_corpus(request: Request, principal: Principal, run_id: str) -> RunCorpus:
    catalog = request.app.state.catalog
    try:
        events = service.run_events_answer(catalog, viewer(request, principal), run_id)["events"]
    except NotFoundError:  # hot here before the catalog flush wrote its row: nothing derived yet
        return RunCorpus()
    with session_scope(catalog) as session:
        return RunCorpus(
            events=events,
            metrics=[
                {"name": m.name, "value": m.value, "text_value": m.text_value, "rules_version": m.rules_version}
                for m in corpus.metrics_of(session, run_id)
            ],
            tags=[{"tag": t.tag, "added_by": t.added_by} for t in corpus.tags_of(session, run_id)],
        )


def events_page(request: Request, principal: Principal, asked: EventsAsked) -> tuple[list[dict[str, Any]], str | None]:
    """A page of events fleet-wide, newest first, and the next page's cursor (None at the end)."""
    flt = service.EventFilter(
        kind=[asked.kind] if asked.kind else [],
        robot=[asked.robot] if asked.robot else [],
        run=[asked.run] if asked.run else [],
        severity=[asked.severity] if asked.severity else [],
        source=asked.source or None,
        limit=PAGE,
        cursor=asked.cursor or None,
    )
    answer = service.events_answer(request.app.state.catalog, viewer(request, principal), flt)
    return answer["events"], answer["next_cursor"]


def add_tags(request: Request, run_id: str, tags: list[str], who: str, now: dt.datetime) -> None:
    service.add_tags(request.app.state.catalog, run_id, tags, who, now)


def remove_tags(request: Request, run_id: str, tags: list[str]) -> None:
    service.remove_tags(request.app.state.catalog, run_id, tags)


def annotate(
    request: Request, principal: Principal, run_id: str, asked: service.Annotation, who: str, now: dt.datetime
) -> None:
    new_id = "ev-" + secrets.token_hex(8)
    service.annotate(request.app.state.catalog, viewer(request, principal), run_id, asked, who, now, new_id)
