"""What the run page shows of the corpus: the run's events (a list, and marks on the timeline
coverage, each opening the web viewer at its window), its metrics and its tags."""

from __future__ import annotations

from typing import Any
from urllib.parse import quote, urlencode

from fastapi import Request

from services.auth.scopes import Principal
from services.console import charts
from services.console import corpus as console_corpus
from services.console.web import PREFIX
from services.runs.run_views import Coverage


def viewer_href(event: dict[str, Any]) -> str:
    """The console's web viewer on the event's run, showing the event's window padded by a few
    seconds (the viewer page signs the recording's link with that window)."""
    start, end = console_corpus.padded(event["timeline_type"], event["start"], event["end"])
    return window_href(event["run_id"], event["timeline"], start, end)


def window_href(run_id: str, timeline: str | None = None, start: int | None = None, end: int | None = None) -> str:
    """The console's web viewer on a run: its window `[start, end]` on `timeline` (inclusive), or
    the whole run without one."""
    run_viewer = f"{PREFIX}/runs/{quote(run_id, safe='')}/viewer"
    if timeline is None or start is None or end is None:
        return run_viewer
    return f"{run_viewer}?{urlencode({'timeline': timeline, 'start': str(start), 'end': str(end)})}"


def event_title(event: dict[str, Any]) -> str:
    said = f": {event['label']}" if event["label"] else ""
    return f"{event['kind']} ({event['severity']}, {event['source']}){said}"


def marks(events: list[dict[str, Any]], cover: Coverage | None) -> list[charts.Mark]:
    """The events on the coverage's timeline, as marks (others are in the list only)."""
    if cover is None:
        return []
    return [
        charts.Mark(e["start"], e["end"], viewer_href(e), event_title(e), e["severity"], e["id"])
        for e in events
        if e["timeline"] == cover.timeline
    ]


def corpus_context(request: Request, principal: Principal, run_id: str, cover: Coverage | None) -> dict[str, Any]:
    """The run page's corpus part: `corpus` (events, metrics, tags), `event_marks` and `viewer_href`."""
    found = console_corpus.run_corpus(request, principal, run_id)
    return {"corpus": found, "event_marks": marks(found.events, cover), "viewer_href": viewer_href}
