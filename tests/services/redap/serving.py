"""A depot node for the catalog-server tests, in process: ingest and retention over local stores and
an embedded catalog, runs uploaded and sealed the way the scheduler seals them, and the catalog
server on a gRPC port of its own (its event loop in a thread), for the `Redap` test client."""

from __future__ import annotations

import asyncio
import datetime as dt
import io
import threading
from dataclasses import dataclass
from pathlib import Path

import grpc
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import create_engine, upgrade
from services.auth.tokens import Auth
from services.ingest.service import IngestReport, IngestService
from services.policies import Policies, Policy
from services.redap import grpc_handler
from services.redap.depot import Depot
from services.retention.service import PROMOTE, Retention, plan, run_plan
from services.rrd import iter_events
from services.sealed.tiers import Tiers
from tests.services.ingest import feeding
from tests.services.nodes import ingest_of, node_of
from tests.services.retention.conftest import Clock
from tests.subprocess_server import free_port

PROMOTE_AFTER = dt.timedelta(minutes=10)


@dataclass
class DepotNode:
    catalog: sessionmaker[Session]
    tiers: Tiers
    clock: Clock
    ingest: IngestService
    retention: Retention

    @property
    def depot(self) -> Depot:
        return Depot(self.retention.node, self.ingest)

    def upload(self, path: Path | bytes) -> IngestReport:
        return feeding.upload(self.ingest, iter_events(io.BytesIO(path) if isinstance(path, bytes) else path))

    def seal_all(self) -> list[str]:
        """Promote every closed hot run, as the scheduler does once they are idle; their ids."""
        self.clock.advance(seconds=PROMOTE_AFTER.total_seconds() + 1)
        outcomes = run_plan(self.retention, plan(self.retention, [PROMOTE]))
        assert all(o.ok for o in outcomes), [o.detail for o in outcomes]
        return [o.action.run_id for o in outcomes]

    def close(self) -> None:
        self.ingest.hot.close()


def build_node(root: Path) -> DepotNode:
    """A node on `root`: hot tier, warm and cold folders, a DuckDB catalog."""
    engine = create_engine(f"duckdb:///{root / 'catalog.duckdb'}")
    upgrade(engine)
    clock = Clock()
    node = node_of(root, sessionmaker(engine), clock=clock, default_robot="robot-0")
    ingest = ingest_of(node)
    retention = Retention(
        node,
        Policies(Policy("default", 30.0, 365.0), ()),
        ingest,
        promote_after=PROMOTE_AFTER,
        promote_below_free_bytes=0,
        restore_days=7.0,
    )
    return DepotNode(node.catalog, node.tiers, clock, ingest, retention)


class CatalogServerThread:
    """The catalog server of `depot` on a free loopback port, its event loop in a thread."""

    def __init__(self, depot: Depot) -> None:
        self.depot = depot
        self.port = free_port()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="catalog-server", daemon=True)
        self._server: grpc.aio.Server | None = None

    def start(self) -> CatalogServerThread:
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self._start(), self._loop).result(timeout=30)
        return self

    async def _start(self) -> None:
        self._server = grpc.aio.server()
        auth = Auth(enabled=False, keys=None, catalog=None)
        grpc_handler.add_to_server(self._server, grpc_handler.CatalogServer(self.depot, auth))
        self._server.add_insecure_port(f"127.0.0.1:{self.port}")
        await self._server.start()

    def stop(self) -> None:
        if self._server is not None:
            asyncio.run_coroutine_threadsafe(self._server.stop(grace=None), self._loop).result(timeout=30)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=30)
        self._loop.close()
