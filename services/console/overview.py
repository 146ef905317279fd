"""The console's overview page: the fleet at a glance (`GET /console/`)."""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import HTMLResponse

from services.console.web import Viewer, console_router, render
from services.runs import fleet

router = console_router()


@router.get("/")
def overview(request: Request, principal: Viewer) -> HTMLResponse:
    """Robots and their last runs, runs per robot per day, data by tier, hot disk and object-store
    usage, recent retention jobs and events, and the runs live now."""
    state = request.app.state
    answer = fleet.overview(state.node, state.ingest)
    return render(request, "overview.html", principal, fleet=answer)
