"""What the catalog server reads: the node (catalog, warm store, clock, how clients reach the
depot) and this node's hot runs. Built once in `server.py` and passed to every call."""

from __future__ import annotations

from dataclasses import dataclass

from services.hot.read import HotRuns
from services.node import Node, OnNode


@dataclass(frozen=True)
class Depot(OnNode):
    node: Node
    hot: HotRuns | None  # None on a node without ingest

    @property
    def public_url(self) -> str:
        """Base URL of the REST API (FLEET_PUBLIC_URL), for direct chunk URLs; "": none."""
        return self.node.settings.public_url
