"""A depot node with its corpus pipeline, built in the test process as `services.server.build`
wires it (ingest observed by the live rules, retention telling sealing), and the scene's runs; and
`fleet serve` itself (auth on, on a Postgres catalog the test reads too) for the end-to-end tests."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import os
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import corpus as corpus_db
from catalog.db import create_engine, session_scope
from catalog.models import Event, RunEvaluation
from services.corpus.pipeline import CorpusPipeline, corpus_pipeline
from services.ingest.service import IngestReport, IngestService
from services.node import Node
from services.policies import Policies, Policy
from services.retention.service import Retention, promote_now
from services.rrd import iter_events
from services.settings import load_settings
from tests.conftest import fresh_catalog
from tests.services.ingest import feeding
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.nodes import ingest_of, node_of
from tests.waiting import wait_for

SCENE = str(Path(__file__).with_name("scene.py"))
CHUNK_ROWS = "8"  # the SDK flushes a chunk every 8 rows: each entity comes in several chunks


def log_scene(out: str, run_id: str, tags: str = "night-shift, dock-2", *, calm: bool = False) -> None:
    env = {**os.environ, "RERUN_FLUSH_NUM_ROWS": CHUNK_ROWS}
    argv = [sys.executable, SCENE, out, run_id, tags, *(["calm"] if calm else [])]
    subprocess.run(argv, check=True, timeout=120, env=env)


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


# --- `fleet serve` ---------------------------------------------------------------------------------


@dataclass
class Served:
    """A `fleet serve` with auth on, and its Postgres catalog, which the test reads too."""

    server: LiveServer
    catalog: sessionmaker[Session]

    @property
    def url(self) -> str:
        return self.server.url

    @property
    def admin(self) -> str:
        """The admin token `fleet serve` wrote at its first start."""
        return (self.server.data_dir / "admin.token").read_text().strip()

    def token(self, *scopes: str, robot: str | None = None) -> str:
        body = {"scopes": list(scopes), "name": f"test-{'-'.join(scopes)}", "robot": robot}
        answer = httpx.post(f"{self.url}/v1/tokens", json=body, headers=self.server.headers, timeout=30)
        assert answer.status_code == 201, answer.text
        return str(answer.json()["token"])

    def fleet(self, token: str, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        """The `fleet` CLI against this server, sending `token`."""
        env = {**os.environ, "FLEET_TOKEN": token, "FLEET_API_URL": self.url}
        done = subprocess.run([FLEET, *args], capture_output=True, text=True, timeout=120, env=env)
        assert not check or done.returncode == 0, f"fleet {' '.join(args)}: {done.stderr}"
        return done

    def stream_scene(self, run_id: str, token: str) -> subprocess.Popen[str]:
        """A robot streaming the scene with the real SDK, its ingest token in its `fleet` property;
        it has sent the first half once it printed READY, and sends the rest after a line on stdin."""
        env = {**os.environ, "RERUN_FLUSH_NUM_ROWS": CHUNK_ROWS, "FLEET_TOKEN": token}
        robot = subprocess.Popen(
            [sys.executable, SCENE, f"grpc:{self.server.grpc_url}", run_id],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=env,
        )
        assert robot.stdout is not None and robot.stdin is not None
        return robot

    def promoted(self, run_id: str, token: str) -> bool:
        """Ask the depot to seal the run now; true once it did (409 while its stream is still open)."""
        headers = {"Authorization": f"Bearer {token}"}
        answer = httpx.post(f"{self.url}/v1/runs/{run_id}/promote", headers=headers, timeout=60)
        return answer.status_code == 200


ServeFactory = Callable[..., Served]


@pytest.fixture
def serve(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ServeFactory]:
    """`serve(rules=TEXT, **settings)`: a `fleet serve` on a fresh Postgres catalog, with auth on, the
    scheduler off and runs sealed only when asked unless `settings` (FLEET_* without the prefix)
    say otherwise; `rules` written as the running version 1 before it starts."""
    with contextlib.ExitStack() as stack:

        def make(rules: str | None = None, **settings: str) -> Served:
            url = stack.enter_context(fresh_catalog("postgres", request, tmp_path))
            engine = create_engine(url)
            stack.callback(engine.dispose)
            catalog = sessionmaker(engine)
            if rules is not None:
                with session_scope(catalog, write=True) as session:
                    corpus_db.add_rules_version(session, rules, "test", dt.datetime.now(dt.UTC))
            defaults = {"auth": "on", "scheduler": "false", "catalog_flush_s": "0.2", "promote_after_s": "3600"}
            server = LiveServer(tmp_path / "data", catalog_url=url, **{**defaults, **settings}).start()
            stack.callback(server.stop)
            return Served(server, catalog)

        yield make
