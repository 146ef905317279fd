"""What people change of a run's corpus on its page (`write` scope): tags added and removed, and
annotations (a person's event on a timeline range). Each goes back to the run's page saying what
happened; a refusal or bad input is shown on the page with its status."""

from __future__ import annotations

import re

from fastapi import Request
from fastapi.responses import Response

from core.clock import utcnow
from services.auth.depends import actor
from services.auth.scopes import Scope
from services.console import corpus as console_corpus
from services.console.run import act
from services.console.web import Form, Viewer, console_router
from services.runs import service as runs_service

router = console_router()


def tags_typed(text: str) -> list[str]:
    """Tags typed in one field, separated by spaces or commas."""
    return [t for t in re.split(r"[\s,]+", text) if t]


@router.post("/runs/{run_id}/tags")
def tag(request: Request, run_id: str, principal: Viewer, form: Form) -> Response:
    def work() -> str:
        tags = tags_typed(str(form.get("tags") or ""))
        console_corpus.add_tags(request.app.state.catalog, run_id, tags, actor(request, principal), utcnow())
        return "tagged"

    return act(request, principal, run_id, Scope.WRITE, work)


@router.post("/runs/{run_id}/tags/remove")
def untag(request: Request, run_id: str, principal: Viewer, form: Form) -> Response:
    def work() -> str:
        console_corpus.remove_tags(request.app.state.catalog, run_id, tags_typed(str(form.get("tag") or "")))
        return "untagged"

    return act(request, principal, run_id, Scope.WRITE, work)


@router.post("/runs/{run_id}/annotate")
def annotate(request: Request, run_id: str, principal: Viewer, form: Form) -> Response:
    def work() -> str:
        state = request.app.state
        run = runs_service.run_answer(
            state.catalog, run_id, None, runs_service.hot_lookup(state.ingest, state.node.default_robot)
        )
        asked = console_corpus.Annotation(
            timeline=str(form.get("timeline") or ""),
            start=str(form.get("start") or ""),
            end=str(form.get("end") or ""),
            label=str(form.get("label") or "").strip(),
        )
        console_corpus.annotate(state.catalog, run, asked, actor(request, principal), utcnow())
        return "annotated"

    return act(request, principal, run_id, Scope.WRITE, work)
