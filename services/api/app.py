"""The FastAPI application: built from the settings, errors mapped once from `FleetError`."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from services import __version__
from services.errors import FleetError
from services.ingest import rest as ingest_rest
from services.ingest.service import IngestService
from services.settings import Settings


def create_app(settings: Settings, ingest: IngestService | None = None) -> FastAPI:
    app = FastAPI(title="Fleet telemetry depot", version=__version__)
    app.state.settings = settings
    app.state.ingest = ingest
    if ingest is not None:
        app.include_router(ingest_rest.router)

    @app.exception_handler(FleetError)
    async def _fleet_error(_: Request, exc: FleetError) -> JSONResponse:
        return JSONResponse(exc.to_dict(), status_code=exc.http_status())

    @app.get("/healthz")
    async def healthz() -> dict[str, str]:
        """The process is up."""
        return {"status": "ok", "version": __version__}

    @app.get("/readyz")
    async def readyz() -> dict[str, str]:
        """The service can take requests."""
        return {"status": "ready"}

    return app
