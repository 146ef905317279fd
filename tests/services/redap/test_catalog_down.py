"""A catalog that does not answer, seen through the catalog service: UNAVAILABLE (REST answers 503),
never UNKNOWN or INTERNAL, so Rerun's clients and operators see a retryable outage."""

from __future__ import annotations

from pathlib import Path

import grpc
import pytest
from sqlalchemy.orm import sessionmaker

from catalog.db import create_engine
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from tests.services.nodes import node_of
from tests.services.redap.catalog_node import CatalogGrpc
from tests.services.redap.client import Redap
from tests.services.redap.depots import status_of
from tests.subprocess_server import free_port


@pytest.mark.postgres
def test_a_catalog_that_refuses_connections_is_unavailable(tmp_path: Path):
    engine = create_engine(f"postgresql+psycopg://postgres@127.0.0.1:{free_port()}/test")  # nothing listens
    server = CatalogGrpc(Depot(node_of(tmp_path, sessionmaker(engine)), None))
    server.start()
    client = Redap(server.port)
    try:
        assert status_of(client, "FindEntries", cloud_pb2.FindEntriesRequest()) == grpc.StatusCode.UNAVAILABLE
    finally:
        client.close()
        server.stop()
        engine.dispose()
