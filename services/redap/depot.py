"""What the catalog server reads: the catalog, the warm store, this node's hot runs, and how
clients reach the depot. Built once in `server.py` and passed to every call."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass, field

from sqlalchemy.orm import Session, sessionmaker

from core.clock import utcnow
from services.hot.read import HotRuns
from services.storage.objectstore import ObjectStore


@dataclass(frozen=True)
class Depot:
    catalog: sessionmaker[Session]
    warm: ObjectStore | None  # None on a node without the sealed tiers
    hot: HotRuns | None  # None on a node without ingest
    public_url: str = ""  # base URL of the REST API (FLEET_PUBLIC_URL), for direct chunk URLs; "": none
    clock: Callable[[], dt.datetime] = field(default=utcnow)
