"""What operators and their tools ask of a node: `/healthz` (the process is up), `/readyz` (the
catalog answers and the hot disk takes writes) and `/metrics` (Prometheus; with several workers on
the host, their figures added up)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, FastAPI
from fastapi.responses import JSONResponse, Response
from prometheus_client import CollectorRegistry

from core.errors import ErrorCode, http_status
from services import __version__
from services.api import metrics as prometheus
from services.api import readiness, worker_metrics
from services.auth.depends import require
from services.auth.scopes import Principal, Scope
from services.ingest.service import IngestService
from services.node import Node

NOT_READY: dict[int | str, dict[str, Any]] = {
    503: {"description": "a part the service needs is not ready: named in `not_ready`, what is wrong in `checks`"}
}


def install(app: FastAPI, node: Node, ingest: IngestService | None) -> None:
    """The three probes; requests are counted from here on (`RequestMetrics`, outermost)."""
    app.get("/healthz")(healthz)
    registry = prometheus.metrics_registry(ingest, node.auth)
    app.add_middleware(prometheus.RequestMetrics, registry=registry)
    _install_metrics(app, registry)
    _install_readyz(app, _checks(node, ingest))


async def healthz() -> dict[str, str]:
    """The process is up."""
    return {"status": "ok", "version": __version__}


def _install_metrics(app: FastAPI, registry: CollectorRegistry) -> None:
    @app.get("/metrics", response_class=Response, responses={200: {"content": {prometheus.CONTENT_TYPE: {}}}})
    async def metrics(_: Annotated[Principal, Depends(require(Scope.READ))], local: bool = False) -> Response:
        """Prometheus text exposition (HELP and TYPE for every metric). With several workers on the
        host (`fleet serve --workers N`), their figures added up; `local=true`: this worker's only."""
        own = await prometheus.exposition(registry)
        siblings: list[Path] = app.state.sibling_sockets
        if local or not siblings:
            return Response(own, media_type=prometheus.CONTENT_TYPE)
        token = app.state.auth.peer_token(f"metrics-{os.getpid()}", None)
        texts = [own.decode(), *await worker_metrics.sibling_expositions(siblings, token)]
        return Response(worker_metrics.merge_expositions(texts), media_type=prometheus.CONTENT_TYPE)


def _checks(node: Node, ingest: IngestService | None) -> list[readiness.Check]:
    """A node that ingests is ready when its catalog answers and its hot disk takes writes."""
    if ingest is None:
        return []
    return [readiness.catalog_check(node.catalog), readiness.hot_disk_check(node.hot.root, node.hot.min_free_bytes)]


def _install_readyz(app: FastAPI, checks: list[readiness.Check]) -> None:
    @app.get("/readyz", responses=NOT_READY)
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
