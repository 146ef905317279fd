from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from sqlalchemy.orm import sessionmaker

from catalog.db import create_engine
from core.clock import utcnow
from services.ingest.service import IngestService
from services.settings import Durability
from tests.services.ingest.factory import ingest_service

Factory = Callable[..., IngestService]


@pytest.fixture
def make_service(tmp_path: Path, fresh_catalog_url: str) -> Iterator[Factory]:
    """Build ingest services on one data dir (a second one = a restart), with a catalog of their own
    (DuckDB or Postgres)."""
    engine = create_engine(fresh_catalog_url)
    made: list[IngestService] = []

    def make(
        *,
        durability: Durability = Durability.OFF,
        min_free_bytes: int = 0,
        max_streams: int = 10,
        close_after_s: float = 60.0,
        clock: Callable[[], dt.datetime] = utcnow,
    ) -> IngestService:
        service = ingest_service(
            tmp_path,
            sessionmaker(engine),
            max_streams=max_streams,
            close_after=dt.timedelta(seconds=close_after_s),
            clock=clock,
            durability=durability,
            min_free_bytes=min_free_bytes,
        )
        made.append(service)
        return service

    yield make
    for service in made:
        service.hot.close()
    engine.dispose()
