"""An ingest service for tests, wired in one place.

Tests build `IngestService` over a hot tier of their own, with or without a catalog; each one that
wired the constructor itself had to change with it. They call `ingest_service` instead and name
only what they are about, so a change to how ingest is put together touches this file alone.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from pathlib import Path

from sqlalchemy.orm import Session, sessionmaker

from core.clock import utcnow
from services.cluster.ownership import Ownership
from services.cluster.relay import Channels
from services.facts.identity import SecretFields
from services.facts.sealed import SealedLookup
from services.hot.store import HotStore
from services.ingest.service import IngestService
from services.rules.observe import ChunkObserver
from services.settings import Durability

DEFAULT_ROBOT = "default-robot"  # the robot of a run whose recording names none


def ingest_service(
    root: Path,
    catalog: sessionmaker[Session] | None = None,
    *,
    default_robot: str = DEFAULT_ROBOT,
    max_streams: int = 10,
    close_after: dt.timedelta = dt.timedelta(seconds=60),
    clock: Callable[[], dt.datetime] = utcnow,
    sealed_lookup: SealedLookup | None = None,
    lookup_timeout_s: float = 2.0,
    durability: Durability = Durability.OFF,
    min_free_bytes: int = 0,
    hot: HotStore | None = None,
    secret_fields: SecretFields | None = None,
    ownership: Ownership | None = None,
    channels: Channels | None = None,
    observer: ChunkObserver | None = None,
) -> IngestService:
    """Ingest with its hot tier in `root / "hot"` (not fsynced, no disk reserve: tests are about
    other things) filing runs in `catalog` (None: no catalog). A second call on the same root is
    a restart: the new service finds the old one's files (`recover()`). `hot`: a hot tier made
    already (a node's: `tests.services.nodes.ingest_of`), in place of one under `root`."""
    hot = hot or HotStore(root / "hot", durability=durability, interval_ms=50, min_free_bytes=min_free_bytes)
    return IngestService(
        hot,
        catalog,
        default_robot=default_robot,
        max_streams=max_streams,
        close_after=close_after,
        clock=clock,
        sealed_lookup=sealed_lookup,
        lookup_timeout_s=lookup_timeout_s,
        secret_fields=secret_fields,
        ownership=ownership,
        channels=channels,
        observer=observer,
    )
