"""The console added to the depot's app: its pages, its static files, and `/` pointing to it."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles

from services.console import (
    datasets,
    events,
    imports,
    interventions,
    login,
    overview,
    run,
    run_edits,
    runs,
    sql,
    viewer,
)
from services.console.web import PREFIX, static_dir

FAVICON = "favicon.svg"
FAVICON_CACHE = {"Cache-Control": "public, max-age=86400"}
ROUTERS = tuple(
    module.router
    for module in (login, overview, runs, run, run_edits, viewer, sql, interventions, events, datasets, imports)
)


def install(app: FastAPI) -> None:
    for router in ROUTERS:
        app.include_router(router)
    app.mount(f"{PREFIX}/static", StaticFiles(directory=static_dir()), name="console-static")

    @app.get("/", include_in_schema=False)
    async def home() -> RedirectResponse:
        """A browser opening the depot's address lands on the console."""
        return RedirectResponse(f"{PREFIX}/", status_code=307)

    @app.get("/favicon.ico", include_in_schema=False)
    async def favicon() -> FileResponse:
        """Browsers ask the origin's root for it whatever the page says (and log a 404 without it)."""
        return FileResponse(Path(static_dir()) / FAVICON, media_type="image/svg+xml", headers=FAVICON_CACHE)

    @app.get(PREFIX, include_in_schema=False)
    async def console_root() -> RedirectResponse:
        return RedirectResponse(f"{PREFIX}/", status_code=307)
