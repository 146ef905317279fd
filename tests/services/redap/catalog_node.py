"""A node's catalog server in the test process: the depot's `CatalogServer` on a gRPC server of its
own event loop (a thread), over a retention test node (ingest, tiers, catalog), and a client that
takes the depot's large FetchChunks answers."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import grpc
import pytest
from sqlalchemy import select

from catalog.db import session_scope
from catalog.models import Dataset
from services.auth.tokens import Auth
from services.redap import grpc_handler
from services.redap.depot import Depot
from tests.services.redap.client import Redap
from tests.services.retention.conftest import Node

MAX_MESSAGE = 256 * 1024 * 1024


@dataclass
class BigRedap(Redap):
    """The test client, taking messages as large as Rerun's clients take (theirs: up to 4 GiB)."""

    def __post_init__(self) -> None:
        options = [("grpc.max_receive_message_length", MAX_MESSAGE), ("grpc.max_send_message_length", MAX_MESSAGE)]
        self.channel = grpc.insecure_channel(f"127.0.0.1:{self.port}", options=options)
        from services.redap.pb import cloud_pb2_grpc

        self.stub = cloud_pb2_grpc.RerunCloudServiceStub(self.channel)


class CatalogGrpc:
    """`CatalogServer` on a grpc.aio server on 127.0.0.1 (a free port), its loop on a thread; with
    `auth`, the depot's token checks (auth off otherwise)."""

    def __init__(self, depot: Depot, auth: Auth | None = None) -> None:
        self.depot = depot
        self.auth = auth
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="catalog-grpc", daemon=True)
        self.server: grpc.aio.Server | None = None
        self.port = 0

    async def _start(self) -> None:
        options = [("grpc.max_receive_message_length", MAX_MESSAGE), ("grpc.max_send_message_length", MAX_MESSAGE)]
        self.server = grpc.aio.server(options=options)
        auth = self.auth or Auth(enabled=False, keys=None, catalog=None)
        grpc_handler.add_to_server(self.server, grpc_handler.CatalogServer(self.depot, auth))
        self.port = self.server.add_insecure_port("127.0.0.1:0")
        await self.server.start()

    def start(self) -> None:
        self.thread.start()
        asyncio.run_coroutine_threadsafe(self._start(), self.loop).result(30)

    def stop(self) -> None:
        if self.server is not None:
            asyncio.run_coroutine_threadsafe(self.server.stop(0), self.loop).result(30)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(30)
        self.loop.close()


@contextmanager
def catalog_server(node: Node) -> Iterator[BigRedap]:
    """The node's catalog server and a client of it."""
    server = CatalogGrpc(Depot(node.context, node.ingest))
    server.start()
    client = BigRedap(server.port)
    try:
        yield client
    finally:
        client.close()
        server.stop()


def entry_of(node: Node, application_id: str) -> str:
    """The dataset entry id of an application, as the catalog holds it."""
    with session_scope(node.catalog) as session:
        found = session.scalars(select(Dataset.entry_id).where(Dataset.name == application_id)).first()
    assert found is not None, f"no dataset for {application_id!r}"
    return str(found)


def count_reads(monkeypatch: pytest.MonkeyPatch, store: object) -> list[tuple[str, int, int | None]]:
    """Record every ranged read of `store`'s kind of object store from now on (key, start, length),
    reading as before: how many reads an answer took, and of what."""
    reads: list[tuple[str, int, int | None]] = []
    real = type(store).get_range  # type: ignore[attr-defined]

    def counted(self: object, key: str, start: int = 0, length: int | None = None) -> bytes:
        reads.append((key, start, length))
        return real(self, key, start, length)  # type: ignore[no-any-return]

    monkeypatch.setattr(type(store), "get_range", counted)
    return reads
