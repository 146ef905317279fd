"""`POST /v1/uploads` never waits for the catalog or the object store on the event loop: asking
whether a new run id was sealed before (the catalog, then the warm store's chunk index) and writing
the run's catalog row before the upload is answered both run on worker threads, so the server
answers other requests while they hang. (tests/services/ingest/test_catalog_outage.py shows the
same for streams against a Postgres that hangs or refuses.)"""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog.db import create_engine, upgrade
from services.api.app import create_app
from services.facts.sealed import SealedInfo
from tests.services.nodes import ingest_of, node_of
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk
HANG_S = 10.0  # a hung call gives up after this: a blocked event loop fails the test instead of hanging it
ANSWER_S = 2.0  # /healthz answers within this of the call hanging


class Hang:
    """A call that does not return until released."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.entered_at = 0.0
        self.released = threading.Event()

    def __call__(self) -> None:
        self.entered_at = time.monotonic()
        self.entered.set()
        self.released.wait(HANG_S)


class HungCatalog(sessionmaker[Session]):
    """A catalog whose sessions wait for `hang` before the database answers."""

    hang: Hang

    def __call__(self, **local_kw: Any) -> Session:
        self.hang()
        return super().__call__(**local_kw)


def test_an_upload_waits_for_the_catalog_and_the_store_on_worker_threads(
    tmp_path: Path, recordings: dict[str, Recording]
):
    engine = create_engine(f"duckdb:///{tmp_path / 'catalog.duckdb'}")
    upgrade(engine)
    catalog = HungCatalog(engine)
    catalog.hang = Hang()
    lookup = Hang()  # the catalog or the warm store does not answer whether the run was sealed

    def sealed_lookup(run_id: str) -> SealedInfo | None:
        lookup()
        return None

    node = node_of(tmp_path, catalog, default_robot="robot")  # settings of tmp_path/data
    ingest = ingest_of(node, sealed_lookup=sealed_lookup, lookup_timeout_s=HANG_S)
    app = create_app(node, ingest)

    async def answers_while(hang: Hang, upload: asyncio.Task[httpx.Response], client: httpx.AsyncClient) -> float:
        await asyncio.to_thread(hang.entered.wait, HANG_S)
        assert (await client.get("/healthz")).status_code == 200
        took = time.monotonic() - hang.entered_at  # a loop blocked by the hung call answers only after it
        assert not upload.done()  # the upload was still waiting for the hung call
        hang.released.set()
        return took

    async def scenario() -> tuple[float, float, httpx.Response]:
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://depot") as client:
            upload = asyncio.create_task(client.post("/v1/uploads", content=recordings["points"].data))
            during_lookup = await answers_while(lookup, upload, client)  # a new run id: was it sealed before?
            during_save = await answers_while(catalog.hang, upload, client)  # its row, before the answer
            return during_lookup, during_save, await asyncio.wait_for(upload, HANG_S)

    try:
        during_lookup, during_save, response = asyncio.run(scenario())
    finally:
        lookup.released.set()
        catalog.hang.released.set()
        node.hot.close()
        engine.dispose()
    assert during_lookup < ANSWER_S and during_save < ANSWER_S
    assert response.status_code == 200 and response.json()["catalog"] == "updated"
    assert response.json()["chunks_new"] > 0
