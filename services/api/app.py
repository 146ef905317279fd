"""The FastAPI application of one node: built from the node (`services.node`) and the sides it
serves, errors mapped once from `FleetError` (`error_answers.py`), probes in `probes.py`."""

from __future__ import annotations

from fastapi import Depends, FastAPI, Request
from fastapi_offline import FastAPIOffline

from core.ids import check_path_id
from services import __version__
from services.analytics import queries_rest
from services.analytics import rest as analytics_rest
from services.analytics.service import Analytics
from services.api import error_answers, probes
from services.api import nodes as nodes_rest
from services.api.cors import Cors
from services.api.redirects import SameOriginRedirects
from services.auth import rest as auth_rest
from services.auth.ratelimit import RateLimits
from services.corpus import backfill_rest
from services.corpus import rest as corpus_rest
from services.datasets import export_rest as dataset_exports_rest
from services.datasets import rest as datasets_rest
from services.edge import rest as edge_rest
from services.edge.context import Edge
from services.imports import rest as imports_rest
from services.ingest.service import IngestService
from services.node import Node
from services.retention import rest as retention_rest
from services.retention.service import Retention
from services.runs import rest as runs_rest
from services.settings import Settings
from services.webhooks import rest as webhooks_rest
from services.webhooks.service import webhooks_of


def path_ids(request: Request) -> None:
    """A dependency of every route: each path parameter is an id of the depot (`check_path_id`),
    else 422 naming it."""
    for name, value in request.path_params.items():
        check_path_id(name, str(value))


def create_app(
    node: Node,
    ingest: IngestService | None = None,
    retention: Retention | None = None,
    analytics: Analytics | None = None,
) -> FastAPI:
    """The REST app of `node`; the routes of a side left out (None) are not installed."""
    app = _bare_app(node.settings)
    _keep(app, node, ingest, retention, analytics)
    _install_routes(app, ingest, retention, analytics)
    error_answers.install(app)
    probes.install(app, node, ingest)
    return app


def _bare_app(settings: Settings) -> FastAPI:
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
    return app


def _keep(
    app: FastAPI, node: Node, ingest: IngestService | None, retention: Retention | None, analytics: Analytics | None
) -> None:
    """What the routes find on `app.state`: the node (and its settings, auth and catalog under their
    own names, where routes have always found them), the sides, and the edge over them."""
    app.state.node = node
    app.state.settings = node.settings
    app.state.auth = node.auth
    app.state.catalog = node.catalog
    app.state.sibling_sockets = []  # other workers of this host (`fleet serve --workers N`), set by the server
    app.state.rate_limits = RateLimits({"sql": node.settings.sql_rate, "download": node.settings.download_rate})
    app.state.ingest = ingest
    app.state.retention = retention
    app.state.analytics = analytics
    if ingest is not None:
        app.state.edge = Edge(node, ingest)
    app.state.webhooks = webhooks_of(node)


def _install_routes(
    app: FastAPI, ingest: IngestService | None, retention: Retention | None, analytics: Analytics | None
) -> None:
    app.include_router(auth_rest.router)
    app.include_router(webhooks_rest.router)
    if analytics is not None:
        app.include_router(analytics_rest.router)
        app.include_router(queries_rest.router)
    if retention is not None:
        app.include_router(retention_rest.router)
    if ingest is not None:
        app.include_router(imports_rest.router)
        app.include_router(runs_rest.router)
        app.include_router(nodes_rest.router)
        app.include_router(edge_rest.router)
        app.include_router(corpus_rest.router)
        app.include_router(backfill_rest.router)  # answers 503 on a node without the corpus pipeline
        app.include_router(datasets_rest.router)
        app.include_router(dataset_exports_rest.router)
