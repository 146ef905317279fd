"""The FastAPI application: built from the settings, errors mapped once from `FleetError`."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path
from typing import Annotated

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from fastapi_offline import FastAPIOffline

from core.clock import utcnow
from core.errors import CATALOG_DOWN, CatalogUnavailableError, ErrorCode, FleetError, http_status
from core.ids import check_path_id
from services import __version__
from services.analytics import queries_rest
from services.analytics import rest as analytics_rest
from services.analytics.service import Analytics
from services.api import metrics as prometheus
from services.api import nodes as nodes_rest
from services.api import readiness, worker_metrics
from services.api.cors import Cors
from services.api.redirects import SameOriginRedirects
from services.auth import rest as auth_rest
from services.auth.bootstrap import open_auth
from services.auth.depends import require
from services.auth.ratelimit import RateLimits
from services.auth.scopes import Principal, Scope
from services.auth.tokens import Auth
from services.edge import rest as edge_rest
from services.edge.context import Edge
from services.ingest import rest as ingest_rest
from services.ingest.service import IngestService
from services.retention import rest as retention_rest
from services.retention.service import Retention
from services.runs import rest as runs_rest
from services.settings import Settings


def path_ids(request: Request) -> None:
    """A dependency of every route: each path parameter is an id of the depot (`check_path_id`),
    else 422 naming it."""
    for name, value in request.path_params.items():
        check_path_id(name, str(value))


def create_app(
    settings: Settings,
    ingest: IngestService | None = None,
    retention: Retention | None = None,
    analytics: Analytics | None = None,
    auth: Auth | None = None,
) -> FastAPI:
    # Swagger UI (/docs) and ReDoc (/redoc) with their scripts and styles served from this process
    # (/static-offline-docs/...), never from a CDN: the docs work on a depot with no internet. No
    # validator badge either: Swagger UI would send the spec's URL to validator.swagger.io.
    # Every route's path parameters are ids, checked here for every route (the console's too,
    # installed later): none reaches a handler or the catalog unless it can be an id.
    app: FastAPI = FastAPIOffline(
        title="Fleet telemetry depot",
        version=__version__,
        swagger_ui_parameters={"validatorUrl": None},
        dependencies=[Depends(path_ids)],
    )
    # Browser viewers (app.rerun.io, a local web viewer) fetch recordings cross-origin by signed link;
    # only the configured origins may send a token.
    app.add_middleware(Cors, origins=settings.cors_origins)
    app.add_middleware(SameOriginRedirects)  # never a Location built from a client's Host header
    app.state.settings = settings
    app.state.sibling_sockets = []  # other workers of this host (`fleet serve --workers N`), set by the server
    catalog = next((side.catalog for side in (ingest, retention, analytics) if side is not None), None)
    app.state.auth = auth = auth or open_auth(settings, catalog)
    app.state.rate_limits = RateLimits({"sql": settings.sql_rate, "download": settings.download_rate})
    app.include_router(auth_rest.router)
    app.state.ingest = ingest
    app.state.retention = retention
    app.state.analytics = analytics
    if analytics is not None:
        app.include_router(analytics_rest.router)
        app.include_router(queries_rest.router)
    if retention is not None:
        app.state.tiers = retention.tiers
        app.include_router(retention_rest.router)
    if ingest is not None:
        app.state.catalog = ingest.catalog
        app.include_router(ingest_rest.router)
        app.include_router(runs_rest.router)
        app.include_router(nodes_rest.router)
    if ingest is not None and ingest.catalog is not None:
        warm = retention.tiers.warm if retention is not None else None
        app.state.edge = Edge(ingest.catalog, ingest, warm, retention.clock if retention is not None else utcnow)
        app.include_router(edge_rest.router)

    @app.exception_handler(RequestValidationError)
    async def _bad_parameter(_: Request, exc: RequestValidationError) -> JSONResponse:
        problems = "; ".join(f"parameter {e['loc'][-1]!r}: {e['msg']}" for e in exc.errors())
        return JSONResponse(
            {"code": ErrorCode.INVALID_ARGUMENT.value, "message": problems},
            status_code=http_status(ErrorCode.INVALID_ARGUMENT),
        )

    @app.exception_handler(FleetError)
    async def _fleet_error(_: Request, exc: FleetError) -> JSONResponse:
        return JSONResponse(exc.to_dict(), status_code=exc.http_status(), headers=exc.headers())

    for catalog_down in CATALOG_DOWN:

        @app.exception_handler(catalog_down)
        async def _catalog_down(_: Request, exc: Exception) -> JSONResponse:
            # The database did not answer (down, restarting, overloaded): not the caller's mistake.
            error = CatalogUnavailableError()
            return JSONResponse(error.to_dict(), status_code=error.http_status())

    @app.get("/healthz")
    async def healthz() -> dict[str, str]:
        """The process is up."""
        return {"status": "ok", "version": __version__}

    registry = prometheus.metrics_registry(ingest, auth)
    app.add_middleware(prometheus.RequestMetrics, registry=registry)

    @app.get("/metrics", response_class=Response, responses={200: {"content": {prometheus.CONTENT_TYPE: {}}}})
    async def metrics(_: Annotated[Principal, Depends(require(Scope.READ))], local: bool = False) -> Response:
        """Prometheus text exposition (HELP and TYPE for every metric). With several workers on the
        host (`fleet serve --workers N`), their figures added up; `local=true`: this worker's only."""
        own = await asyncio.to_thread(prometheus.exposition, registry)
        siblings: list[Path] = app.state.sibling_sockets
        if local or not siblings:
            return Response(own, media_type=prometheus.CONTENT_TYPE)
        token = app.state.auth.peer_token(f"metrics-{os.getpid()}", None)
        texts = [own.decode(), *await worker_metrics.sibling_expositions(siblings, token)]
        return Response(worker_metrics.merge_expositions(texts), media_type=prometheus.CONTENT_TYPE)

    checks: list[readiness.Check] = []
    if ingest is not None:
        if ingest.catalog is not None:
            checks.append(readiness.catalog_check(ingest.catalog))
        checks.append(readiness.hot_disk_check(ingest.hot.root, ingest.hot.min_free_bytes))

    @app.get(
        "/readyz",
        responses={
            503: {
                "description": "a part the service needs is not ready: named in `not_ready`, what is wrong in `checks`"
            }
        },
    )
    async def readyz() -> JSONResponse:
        """The service can take requests: the catalog answers and the hot disk takes writes."""
        statuses = await readiness.check_all(checks)
        failed = [name for name, status in statuses.items() if status != readiness.OK]
        if not failed:
            return JSONResponse({"status": "ready", "checks": statuses})
        code = ErrorCode.UNAVAILABLE
        return JSONResponse(
            {
                "code": code.value,
                "status": "not ready",
                "not_ready": failed,
                "checks": statuses,
                "message": "not ready: " + "; ".join(f"{name}: {statuses[name]}" for name in failed),
            },
            status_code=http_status(code),
        )

    return app
