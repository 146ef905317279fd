"""What the catalog server reads: the node (catalog, warm store, clock, how clients reach the
depot) and this node's hot runs. Built once in `server.py` and passed to every call."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass

from sqlalchemy.orm import Session, sessionmaker

from services.hot.read import HotRuns
from services.node import Node
from services.storage.objectstore import ObjectStore


@dataclass(frozen=True)
class Depot:
    node: Node
    hot: HotRuns | None  # None on a node without ingest

    # The node's, named here as the catalog server's modules have always named them.
    @property
    def catalog(self) -> sessionmaker[Session]:
        return self.node.catalog

    @property
    def warm(self) -> ObjectStore:
        return self.node.tiers.warm

    @property
    def clock(self) -> Callable[[], dt.datetime]:
        return self.node.clock

    @property
    def public_url(self) -> str:
        """Base URL of the REST API (FLEET_PUBLIC_URL), for direct chunk URLs; "": none."""
        return self.node.settings.public_url
