"""Fixtures shared by the services' test packages."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from services.hot.store import HotStore
from services.settings import Durability
from tests.services.ingest.live_server import LiveServer


@pytest.fixture
def server(tmp_path: Path) -> Iterator[LiveServer]:
    """`fleet serve` of this test's own, on an empty data dir. A module whose tests can share one
    (they do not kill it, and none needs it empty) defines a module-scoped `server` instead."""
    live = LiveServer(tmp_path / "data").start()
    yield live
    live.stop()


@pytest.fixture
def hot_store(tmp_path: Path) -> Iterator[HotStore]:
    """A hot tier of this test's own (not fsynced, no disk reserve), closed after it."""
    hot = HotStore(tmp_path / "hot", durability=Durability.OFF, interval_ms=50, min_free_bytes=0)
    yield hot
    hot.close()
