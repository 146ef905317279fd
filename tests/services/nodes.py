"""A node context (`services.node.Node`) for tests that build a node's sides by hand, and the
ingest service on it, wired as `services.server.build` wires them."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from core.clock import utcnow
from services.auth.bootstrap import open_auth
from services.facts.identity import SecretFields
from services.hot.store import HotStore
from services.ingest.service import IngestService
from services.lakehouse.tables import Lakehouse
from services.node import Node
from services.sealed.tiers import Tiers, sealed_lookup
from services.settings import Durability, Settings, load_settings
from services.storage.objectstore import open_store
from tests.services.ingest.factory import ingest_service


def local_tiers(root: Path) -> Tiers:
    """Warm and cold stores in two folders under `root`."""
    return Tiers(open_store((root / "warm").as_uri()), open_store((root / "cold").as_uri()))


def node_of(
    root: Path,
    catalog: sessionmaker[Session],
    *,
    settings: Settings | None = None,
    tiers: Tiers | None = None,
    clock: Callable[[], dt.datetime] = utcnow,
    default_robot: str | None = None,
    secret_fields: SecretFields | None = None,
    min_free_bytes: int = 0,
    lakehouse: Lakehouse | None = None,
) -> Node:
    """A node over `catalog`: its hot tier in `root`/hot, its stores `tiers` (else folders under
    `root`), `settings` (else those of a data dir `root`/data) and the auth they say."""
    settings = settings or load_settings(data_dir=root / "data", scheduler=False)
    settings.data_dir.mkdir(parents=True, exist_ok=True)  # where auth keeps its signing key
    return Node(
        settings=settings,
        catalog=catalog,
        tiers=tiers or local_tiers(root),
        hot=HotStore(root / "hot", durability=Durability.OFF, interval_ms=50, min_free_bytes=min_free_bytes),
        auth=open_auth(settings, catalog),
        default_robot=default_robot or settings.default_robot,
        secret_fields=secret_fields or SecretFields(settings.secret_fields),
        clock=clock,
        lakehouse=lakehouse,
    )


def ingest_of(node: Node, **more: Any) -> IngestService:
    """The ingest service of `node` (wired by the tests' one factory), asking its catalog and warm
    store what was sealed before; `more`: other arguments of `ingest_service`."""
    return ingest_service(
        node.settings.data_dir,
        node.catalog,
        hot=node.hot,
        default_robot=node.default_robot,
        clock=node.clock,
        sealed_lookup=more.pop("sealed_lookup", sealed_lookup(node.catalog, node.tiers)),
        secret_fields=node.secret_fields,
        ownership=node.ownership,
        channels=node.channels,
        **more,
    )
