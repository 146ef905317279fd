"""What the sides of one depot node share: built once by `fleet serve` (`server.build`) and passed
down, so no service is asked where the catalog or the stores are, and none keeps its own copy.

It sits above ingest and the sealed format (it names their stores) and below every service that
reads it (analytics, retention, runs, edge, the REST app, the catalog server). Ingest takes the
parts it needs one by one: it is built from these same values, below the node.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass

from sqlalchemy.orm import Session, sessionmaker

from core.clock import utcnow
from services.auth.tokens import Auth
from services.cluster.ownership import Ownership
from services.cluster.relay import Channels
from services.facts.identity import SecretFields
from services.hot.store import HotStore
from services.lakehouse.tables import Lakehouse
from services.sealed.tiers import Tiers
from services.settings import Settings
from services.storage.objectstore import ObjectStore


@dataclass(frozen=True)
class Node:
    """One depot node's settings, catalog, stores and clock, and who it is among many nodes."""

    settings: Settings
    catalog: sessionmaker[Session]
    tiers: Tiers  # the warm and cold stores sealed runs live in
    hot: HotStore  # this node's hot tier on its own disk
    auth: Auth  # checks callers' tokens; signs what this node asks or hands to other nodes
    default_robot: str  # robot id of runs that name none (FLEET_DEFAULT_ROBOT)
    secret_fields: SecretFields  # property fields stripped at ingest and sealing (FLEET_SECRET_FIELDS)
    clock: Callable[[], dt.datetime] = utcnow
    # Many nodes on one catalog: who owns which run, and channels to the other nodes' peer ports.
    # Both None on a node that files every run itself (one node, or an embedded catalog).
    ownership: Ownership | None = None
    channels: Channels | None = None
    # The Iceberg tables outside engines read (FLEET_LAKEHOUSE); None when turned off.
    lakehouse: Lakehouse | None = None


class OnNode:
    """For a side of the node (`Analytics`, `Edge`, the catalog server's `Depot`) that keeps its
    `node`: the parts its modules read, by the names they have always used."""

    node: Node

    @property
    def catalog(self) -> sessionmaker[Session]:
        return self.node.catalog

    @property
    def warm(self) -> ObjectStore:
        """Where sealed runs, their chunk indexes and the extracted tables are."""
        return self.node.tiers.warm

    @property
    def clock(self) -> Callable[[], dt.datetime]:
        return self.node.clock
