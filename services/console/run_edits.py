"""What people change of a run's corpus on its page (`write` scope): tags added and removed, and
annotations (a person's event on a timeline range), through the corpus service as the REST API
does. Each goes back to the run's page saying what happened; a refusal or bad input is shown on
the page with its status."""

from __future__ import annotations

import re

from fastapi import Request
from fastapi.responses import Response

from services.auth.depends import actor
from services.auth.scopes import Scope
from services.console import corpus as console_corpus
from services.console.run import act
from services.console.web import Form, Viewer, console_router
from services.corpus.service import Annotation

router = console_router()


def tags_typed(text: str) -> list[str]:
    """Tags typed in one field, separated by spaces or commas."""
    return [t for t in re.split(r"[\s,]+", text) if t]


def _text(form: Form, name: str) -> str:
    return str(form.get(name) or "").strip()


@router.post("/runs/{run_id}/tags")
def tag(request: Request, run_id: str, principal: Viewer, form: Form) -> Response:
    def work() -> str:
        now = request.app.state.node.clock()
        console_corpus.add_tags(request, run_id, tags_typed(_text(form, "tags")), actor(request, principal), now)
        return "tagged"

    return act(request, principal, run_id, Scope.WRITE, work)


@router.post("/runs/{run_id}/tags/remove")
def untag(request: Request, run_id: str, principal: Viewer, form: Form) -> Response:
    def work() -> str:
        console_corpus.remove_tags(request, run_id, tags_typed(_text(form, "tag")))
        return "untagged"

    return act(request, principal, run_id, Scope.WRITE, work)


@router.post("/runs/{run_id}/annotate")
def annotate(request: Request, run_id: str, principal: Viewer, form: Form) -> Response:
    def work() -> str:
        asked = Annotation(
            timeline=_text(form, "timeline"),
            start=_text(form, "start"),
            end=_text(form, "end") or None,
            label=_text(form, "label"),
        )
        now = request.app.state.node.clock()
        console_corpus.annotate(request, principal, run_id, asked, actor(request, principal), now)
        return "annotated"

    return act(request, principal, run_id, Scope.WRITE, work)
