"""Fixtures of the edge suites: an edge over a catalog of its own (DuckDB and Postgres), catalog runs
made by hand, principals of each kind, and a node (ingest + retention over local folders) fed runs
logged with the real SDK."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from core.errors import FleetError
from core.states import RunStatus, Tier
from services.auth.scopes import Principal, Scope
from services.edge.context import Edge
from services.rrd import ArrowMessage, iter_events
from services.rrd.chunk import chunk_meta
from services.sealed.tiers import Tiers
from services.storage.objectstore import open_store
from tests.catalog.records import run_record
from tests.services.nodes import node_of
from tests.services.retention.conftest import Clock, Node, NodeFactory, log_run, make_node

__all__ = ["make_node"]  # a fixture of the retention suites, used here as is

ROBOT, OTHER_ROBOT = "robot-7", "robot-a"
READER = Principal("reader", frozenset({Scope.READ}), token_id="t-read")
WRITER = Principal("writer", frozenset({Scope.WRITE}), token_id="t-write")
ADMIN = Principal("admin", frozenset({Scope.ADMIN}), token_id="t-admin")


@contextmanager
def refused(kind: type[FleetError], status: int, *says: str) -> Iterator[None]:
    """The block raises a `kind` error, answered with HTTP `status`, whose message says each of `says`."""
    with pytest.raises(kind) as info:
        yield
    assert info.value.http_status() == status, info.value
    for text in says:
        assert text in info.value.message, info.value.message


def robot_token(robot: str = ROBOT) -> Principal:
    """A robot's ingest token, as the depot issues it (bound to its robot)."""
    return Principal(robot, frozenset({Scope.INGEST}), robot, token_id=f"t-{robot}")


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def edge(catalog: sessionmaker[Session], clock: Clock, tmp_path: Path) -> Edge:
    """The edge of a node that ingests nothing (no hot runs; nothing in its warm store): pulls and
    robot copies."""
    return Edge(node_of(tmp_path, catalog, clock=clock))


def add_run(
    catalog: sessionmaker[Session], run_id: str, *, robot: str = ROBOT, tier: str = Tier.WARM, status: str = "closed"
) -> None:
    """A run row as the catalog would hold it (the figures do not matter here)."""
    now = dt.datetime.now(dt.UTC)
    record = run_record(
        run_id, now, robot_id=robot, application_id="edge-test", status=RunStatus(status), tier=Tier(tier), bytes=1
    )
    with session_scope(catalog, write=True) as session:
        queries.save_run(session, record, now)


# --- a node fed runs logged with the real SDK ---------------------------------------------------------

RUN = "edge-run-1"


@dataclass(frozen=True)
class SdkRuns:
    first: Path  # a run as the robot logged it
    later: Path  # more chunks of the same recording id, logged later (late data)


@pytest.fixture(scope="session")
def sdk_runs(tmp_path_factory: pytest.TempPathFactory) -> SdkRuns:
    folder = tmp_path_factory.mktemp("edge-runs")
    with ThreadPoolExecutor(2) as pool:  # one SDK process each, side by side
        first = pool.submit(log_run, folder / "first.rrd", RUN, entities=3, frames=6, points=50, robot=ROBOT)
        later = pool.submit(
            log_run, folder / "later.rrd", RUN, entities=2, frames=3, points=50, robot=ROBOT, text=False
        )
        return SdkRuns(first.result(), later.result())


def chunk_ids(path: Path) -> list[str]:
    """The chunk ids of a recording as an agent sends them: 32 lowercase hex digits."""
    return [chunk_meta(e).chunk_id.hex() for e in iter_events(path) if isinstance(e, ArrowMessage)]


@pytest.fixture
def node(make_node: NodeFactory, tmp_path: Path) -> Node:
    """Ingest and retention on local folders (warm, cold), with a catalog of their own."""
    return make_node(Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri())))


@pytest.fixture
def node_edge(node: Node) -> Edge:
    """The edge as the app wires it on that node: its catalog, its hot runs, its warm store."""
    return Edge(node.context, node.ingest)
