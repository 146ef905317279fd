"""A depot node with its corpus pipeline, built in the test process as `services.server.build`
wires it (ingest observed by the live rules, retention telling sealing), and the scene's runs."""

from __future__ import annotations

import datetime as dt
import io
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus as corpus_db
from catalog.db import session_scope
from catalog.models import Event, RunEvaluation
from services.corpus.pipeline import CorpusPipeline, corpus_pipeline
from services.ingest.service import IngestReport, IngestService
from services.node import Node
from services.policies import Policies, Policy
from services.retention.service import Retention, promote_now
from services.rrd import iter_events
from services.settings import load_settings
from tests.services.ingest import feeding
from tests.services.nodes import ingest_of, node_of
from tests.waiting import wait_for

SCENE = str(Path(__file__).with_name("scene.py"))
CHUNK_ROWS = "8"  # the SDK flushes a chunk every 8 rows: each entity comes in several chunks


def log_scene(out: str, run_id: str, tags: str = "night-shift, dock-2") -> None:
    env = {**os.environ, "RERUN_FLUSH_NUM_ROWS": CHUNK_ROWS}
    subprocess.run([sys.executable, SCENE, out, run_id, tags], check=True, timeout=120, env=env)


@pytest.fixture(scope="session")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str], bytes]:
    """The scene's recording under a run id (logged once per id)."""
    folder = tmp_path_factory.mktemp("scenes")
    made: dict[str, bytes] = {}

    def make(run_id: str) -> bytes:
        if run_id not in made:
            path = folder / f"{run_id}.rrd"
            log_scene(str(path), run_id)
            made[run_id] = path.read_bytes()
        return made[run_id]

    return make


@dataclass
class Depot:
    node: Node
    ingest: IngestService
    corpus: CorpusPipeline
    retention: Retention

    def apply(self, text: str) -> int:
        """A new rules version, as `fleet rules apply` makes it; once the live rules run it, if started."""
        with session_scope(self.node.catalog, write=True) as session:
            version = corpus_db.add_rules_version(session, text, "test", self.node.clock())[0].version
        if self.corpus.live._thread is not None:
            wait_for(lambda: self.corpus.live.version == version, timeout=30, what=f"live rules at version {version}")
        return version

    def upload(self, data: bytes) -> IngestReport:
        return feeding.upload(self.ingest, iter_events(io.BytesIO(data)))

    def seal(self, run_id: str) -> dict[str, Any]:
        return promote_now(self.retention, run_id)

    def evaluation(self, run_id: str) -> RunEvaluation | None:
        with session_scope(self.node.catalog) as session:
            found = session.get(RunEvaluation, run_id)
            if found is not None:
                session.expunge(found)
            return found

    def events(self, run_id: str) -> list[Event]:
        with session_scope(self.node.catalog) as session:
            found = corpus_db.events_of_run(session, run_id)
            session.expunge_all()
            return found

    def metrics(self, run_id: str) -> dict[str, tuple[float | None, str | None, int]]:
        with session_scope(self.node.catalog) as session:
            return {m.name: (m.value, m.text_value, m.rules_version) for m in corpus_db.metrics_of(session, run_id)}

    def tags(self, run_id: str) -> dict[str, str]:
        with session_scope(self.node.catalog) as session:
            return {t.tag: t.added_by for t in corpus_db.tags_of(session, run_id)}


DepotFactory = Callable[..., Depot]


@pytest.fixture
def make_depot(tmp_path: Path, catalog: sessionmaker[Session]) -> Iterator[DepotFactory]:
    made: list[Depot] = []

    def make(*, start: bool = True, queue_chunks: int | None = None, **settings: Any) -> Depot:
        data = tmp_path / "data"
        node = node_of(tmp_path, catalog, settings=load_settings(data_dir=data, scheduler=False, **settings))
        corpus = corpus_pipeline(node, **({"queue_chunks": queue_chunks} if queue_chunks else {}))
        ingest = ingest_of(node, observer=corpus.live)
        corpus.attach(ingest)
        retention = Retention(
            node,
            Policies(Policy("default", 30, 365)),
            ingest,
            promote_after=dt.timedelta(0),
            on_sealed=corpus.sealing.sealed,
        )
        depot = Depot(node, ingest, corpus, retention)
        if start:
            corpus.start()
        made.append(depot)
        return depot

    yield make
    for depot in made:
        depot.corpus.stop()
        depot.ingest.hot.close()
