"""The depot and the link to it that the agent's end-to-end tests share: `fleet serve` as a real
process, and the two proxies (gRPC, REST) a test cuts and restores."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.services.agent.harness import Link
from tests.services.ingest.live_server import LiveServer


@pytest.fixture
def depot(tmp_path: Path) -> Iterator[LiveServer]:
    server = LiveServer(tmp_path / "depot").start()
    yield server
    server.stop()


@pytest.fixture
def link(depot: LiveServer) -> Iterator[Link]:
    proxies = Link(depot)
    yield proxies
    proxies.close()
