"""The console's Events page (`GET /console/events`): events fleet-wide, newest first, filtered by
kind, robot, severity, source and run, with cursor paging; each row links to its run and opens the
web viewer at its window. The filters are query parameters, so a view can be kept and shared.

Each row says where the event's window is (`data`: its state and its pulls); one held on the robot
(over its trigger's budget) or left there (its pulls stopped before sending any) has a button that
pulls it (`write` scope: `POST /console/events/EVENT/pull`, as `POST /v1/events/EVENT/pull`)."""

from __future__ import annotations

from dataclasses import asdict
from urllib.parse import urlencode, urlsplit

from fastapi import Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response

from catalog.edge import ON_ROBOT, OVER_BUDGET
from core.errors import FleetError, InvalidArgumentError, UnavailableError
from services.auth.depends import actor
from services.auth.scopes import Principal, Scope
from services.console import corpus as console_corpus
from services.console.corpus import EventsAsked
from services.console.run_corpus import viewer_href
from services.console.web import PREFIX, Form, Viewer, console_router, render
from services.edge import triggers

router = console_router()
FILTERS = ("kind", "robot", "severity", "source", "run")
PULLABLE = (OVER_BUDGET, ON_ROBOT)  # data states whose window a person may pull from the page
# What pulling an event did, shown on the page it leads back to (fixed texts: nothing from the URL).
NOTICES = {
    "pulled": "Pull queued: the robot's agent sends the event's window when it next polls.",
    "pull-pending": "A pull of this event was pending already: nothing new was asked of the robot.",
}


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
    return _page(request, principal, asked_of(request), notice=NOTICES.get(request.query_params.get("done") or ""))


def _page(
    request: Request,
    principal: Principal,
    asked: EventsAsked,
    *,
    notice: str | None = None,
    refused: FleetError | None = None,
) -> HTMLResponse:
    problem, status = (refused.message, refused.http_status()) if refused is not None else (None, 200)
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
        notice=notice,
        pullable=PULLABLE,
    )


@router.post("/events/{event_id}/pull")
def pull_event(request: Request, event_id: str, principal: Viewer, form: Form) -> Response:
    """Pull the event's window; back to the page the button was on, saying what happened (a refusal
    shown on the Events page with its status)."""
    back = _events_href(str(form.get("back") or ""))
    try:
        principal.require(Scope.WRITE)
        edge = getattr(request.app.state, "edge", None)
        if edge is None:
            raise UnavailableError("this node keeps no pulls (it has no catalog of robots' runs): ask another node")
        _, created = triggers.pull_event(edge, event_id, actor(request, principal))
    except FleetError as exc:
        return _page(request, principal, EventsAsked(), refused=exc)
    done = "pulled" if created else "pull-pending"
    return RedirectResponse(f"{back}{'&' if '?' in back else '?'}done={done}", status_code=303)


def _events_href(back: str) -> str:
    """The Events page the form was posted from (its filters), never another page or site."""
    parts = urlsplit(back)
    if parts.scheme or parts.netloc or parts.path != f"{PREFIX}/events":
        return f"{PREFIX}/events"
    return back
