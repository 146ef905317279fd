"""The console's Events page (`GET /console/events`): events fleet-wide, newest first, filtered by
kind, robot, severity, source and run, with cursor paging; each row links to its run and opens the
web viewer at its window. The filters are query parameters, so a view can be kept and shared."""

from __future__ import annotations

from dataclasses import asdict
from urllib.parse import urlencode

from fastapi import Request
from fastapi.responses import HTMLResponse

from core.errors import InvalidArgumentError
from services.console import corpus as console_corpus
from services.console.corpus import EventsAsked
from services.console.run_corpus import viewer_href
from services.console.web import PREFIX, Viewer, console_router, render

router = console_router()
FILTERS = ("kind", "robot", "severity", "source", "run")


def asked_of(request: Request) -> EventsAsked:
    params = request.query_params

    def one(name: str) -> str:
        return (params.get(name) or "").strip()

    return EventsAsked(
        kind=one("kind"),
        robot=one("robot"),
        severity=one("severity"),
        source=one("source"),
        run=one("run"),
        cursor=one("cursor"),
    )


def href(asked: EventsAsked, **changes: str) -> str:
    """This page's URL with some parameters changed (a filter, the next page's cursor)."""
    given = {**asdict(asked), **changes}
    query = urlencode([(name, given[name]) for name in (*FILTERS, "cursor") if given[name]])
    return f"{PREFIX}/events" + (f"?{query}" if query else "")


@router.get("/events")
def events_page(request: Request, principal: Viewer) -> HTMLResponse:
    asked = asked_of(request)
    problem, status = None, 200
    try:
        found, next_cursor = console_corpus.events_page(request, principal, asked)
    except InvalidArgumentError as exc:  # a bad severity or cursor: the page says so
        found, next_cursor, problem, status = [], None, exc.message, exc.http_status()
    return render(
        request,
        "events.html",
        principal,
        status=status,
        asked=asked,
        events=found,
        severities=console_corpus.SEVERITIES,
        next_href=href(asked, cursor=next_cursor) if next_cursor else None,
        first_href=href(asked, cursor="") if asked.cursor else None,
        href=href,
        viewer_href=viewer_href,
        problem=problem,
    )
