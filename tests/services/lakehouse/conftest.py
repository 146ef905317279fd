"""The lakehouse tests' catalog (DuckDB or Postgres, fresh per test) and the lakehouse on it over
the test module's `tiers` (a folder, or SeaweedFS)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import create_engine
from services.lakehouse.tables import Lakehouse, open_lakehouse
from services.sealed.tiers import Tiers


@pytest.fixture
def catalog(fresh_catalog_url: str) -> Iterator[sessionmaker[Session]]:
    engine = create_engine(fresh_catalog_url)
    yield sessionmaker(engine)
    engine.dispose()


@pytest.fixture
def lake(fresh_catalog_url: str, tiers: Tiers) -> Iterator[Lakehouse]:
    opened = open_lakehouse(fresh_catalog_url, tiers.warm)
    yield opened
    opened.close()
