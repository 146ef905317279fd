"""REST: `GET /v1/nodes`, the depot's processes on this catalog and the runs each owns."""

from __future__ import annotations

import asyncio
import datetime as dt
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from sqlalchemy.orm import Session, sessionmaker

from catalog import nodes
from catalog.db import session_scope
from core.clock import iso_utc
from services.auth.depends import require
from services.auth.scopes import Principal, Scope

router = APIRouter()


def node_list(catalog: sessionmaker[Session], lease_s: float) -> list[dict[str, Any]]:
    with session_scope(catalog) as session:
        rows = nodes.nodes(session, dt.timedelta(seconds=lease_s))
    return [
        {
            "id": n.id,
            "peer_addr": n.peer_addr,
            "version": n.version,
            "started_at": iso_utc(n.started_at),
            "heartbeat_at": iso_utc(n.heartbeat_at),
            "alive": n.alive,
            "runs_owned": n.runs_owned,
        }
        for n in rows
    ]


@router.get("/v1/nodes", summary="The depot's processes on this catalog: alive or not, and the runs each owns")
async def list_nodes(request: Request, _: Annotated[Principal, Depends(require(Scope.READ))]) -> dict[str, Any]:
    """Every node that ever heart-beat on this catalog (a single embedded node lists none). A node is
    alive while its heartbeat is fresher than FLEET_LEASE_S; the runs of one that is not are taken over
    by the next node that receives their chunks."""
    catalog = request.app.state.catalog
    lease_s = request.app.state.settings.lease_s
    return {"nodes": await asyncio.to_thread(node_list, catalog, lease_s)}
