"""A catalog that is down or hung never stops ingest: streams and uploads keep going to the hot
tier, the event loop never waits for the database, and the catalog catches up when it is back.
The Postgres catalog is reached through a loopback proxy the test makes refuse or hang."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import event as sql_event
from sqlalchemy.engine import Engine, make_url
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import create_engine, session_scope
from services.ingest.service import IngestService
from services.rrd import ArrowMessage, iter_events
from services.sealed.tiers import Tiers, sealed_lookup
from services.storage.objectstore import open_store
from tests.postgres import temporary_database
from tests.services.ingest.factory import ingest_service
from tests.services.retention.conftest import log_run
from tests.tcp_proxy import FORWARD, HANG, REFUSE, TcpProxy, tcp_proxy

pytestmark = [pytest.mark.postgres, pytest.mark.sdk]


@pytest.fixture
def proxied_catalog(migrated_postgres_template: str) -> Iterator[tuple[sessionmaker[Session], TcpProxy]]:
    with temporary_database("fleet_outage", template=migrated_postgres_template) as url:
        parsed = make_url(url)
        with tcp_proxy(parsed.host or "127.0.0.1", parsed.port or 5432) as proxy:
            engine = create_engine(parsed.set(host="127.0.0.1", port=proxy.port).render_as_string(hide_password=False))
            yield sessionmaker(engine), proxy
            proxy.set_mode(REFUSE)  # frees threads still waiting on a hung connection
            engine.dispose()


class LoopLag:
    """The longest the event loop was kept from running a 20 ms timer."""

    def __init__(self) -> None:
        self.worst = 0.0
        self._task: asyncio.Task[None] | None = None

    async def _watch(self) -> None:
        while True:
            start = time.monotonic()
            await asyncio.sleep(0.02)
            self.worst = max(self.worst, time.monotonic() - start - 0.02)

    def start(self) -> None:
        self._task = asyncio.create_task(self._watch())

    def stop(self) -> None:
        assert self._task is not None
        self._task.cancel()


async def stream(ingest: IngestService, path: Path, *, live: bool) -> str:
    """Send a recording as a live stream or an upload; returns what the upload answer says of the catalog."""
    source = ingest.open_source(live=live)
    for event in iter_events(path):
        await ingest.prepare(source, event)
        ingest.accept(source, event)
        await asyncio.sleep(0)  # as a network handler would, between messages
    if live:
        ingest.close_source(source)
        return "live"
    return (await ingest.finish_upload(source, timeout_s=1.0)).catalog


class DatabaseThreads:
    """The threads that connected to the catalog or took a connection from its pool: the event
    loop's must never be among them (a call there waits as long as the database does)."""

    def __init__(self, engine: Engine) -> None:
        self.seen: set[int] = set()
        sql_event.listen(engine, "do_connect", self._saw)  # before connecting: a hung handshake still counts
        sql_event.listen(engine, "checkout", self._saw)

    def _saw(self, *_: object) -> None:
        self.seen.add(threading.get_ident())


def chunk_count(path: Path) -> int:
    return sum(isinstance(e, ArrowMessage) for e in iter_events(path))


def test_ingest_goes_on_while_the_catalog_is_hung_or_down_and_it_catches_up(
    proxied_catalog: tuple[sessionmaker[Session], TcpProxy], tmp_path: Path
):
    catalog, proxy = proxied_catalog
    tiers = Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri()))
    ingest = ingest_service(
        tmp_path, catalog, default_robot="robot", sealed_lookup=sealed_lookup(catalog, tiers), lookup_timeout_s=0.5
    )
    runs = {name: log_run(tmp_path / f"{name}.rrd", name, frames=20) for name in ("live-a", "upload-b", "down-c")}
    database = DatabaseThreads(catalog.kw["bind"])
    loop_thread = threading.get_ident()  # asyncio.run below runs the loop on this thread

    async def scenario() -> dict[str, str]:
        lag = LoopLag()
        lag.start()
        proxy.set_mode(HANG)  # the database accepts connections and never answers
        answers = dict(
            zip(
                ("live-a", "upload-b"),
                await asyncio.gather(
                    stream(ingest, runs["live-a"], live=True), stream(ingest, runs["upload-b"], live=False)
                ),
                strict=True,
            )
        )
        proxy.set_mode(REFUSE)  # the database is down
        answers["down-c"] = await stream(ingest, runs["down-c"], live=False)
        lag.stop()
        answers["lag"] = f"{lag.worst:.3f}"
        return answers

    started = time.monotonic()
    answers = asyncio.run(scenario())
    assert time.monotonic() - started < 20  # no stream waited for the database
    assert database.seen and loop_thread not in database.seen  # the event loop never waited for it,
    assert float(answers["lag"]) < 2.0, answers  # nor for anything else long (a loaded machine lags too)
    assert answers["upload-b"] == answers["down-c"] == "pending"  # said so, and the data is kept:
    for name, path in runs.items():
        assert ingest.runs[name].chunk_ids and len(ingest.runs[name].chunk_ids) == chunk_count(path)

    proxy.set_mode(FORWARD)  # back: the next flush writes every run
    ingest.flush_catalog()
    with session_scope(catalog) as session:
        for name in runs:
            run = queries.get_run(session, name)
            assert run is not None and run.chunks == chunk_count(runs[name]) and run.status == "closed"
    ingest.hot.close()
