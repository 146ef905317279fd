"""The queries `benchmarks/catalog_scale.py` times, each through the code that answers it: the
service functions the REST handlers and the console call, the REST app in-process for what `fleet
runs ls` asks, and the catalog server's segment table scan."""

from __future__ import annotations

import contextlib
import datetime as dt
import tempfile
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import sqlalchemy as sa
from sqlalchemy.orm import Session, sessionmaker

from benchmarks.catalog_scale_fill import ROBOTS, policies, robot_name
from catalog import queries as catalog_queries
from catalog.db import session_scope
from catalog.models import Run
from core.states import Tier
from services.api.app import create_app
from services.auth.bootstrap import open_auth
from services.auth.scopes import Principal, Scope
from services.facts.identity import SecretFields
from services.hot.store import HotStore
from services.node import Node
from services.redap import segments
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from services.retention.service import ACTIONS, Retention, plan_answer
from services.runs import fleet, totals
from services.runs import rest as runs_rest
from services.runs.service import RunFilter, run_answer, runs_answer
from services.runtime import freeze_startup_objects
from services.sealed.tiers import Tiers
from services.settings import Durability, load_settings
from services.storage.objectstore import open_store

DATASET = "inspection"  # the dataset whose segment table is scanned (a quarter of the runs)
RUN_PAGES = 64  # runs whose pages are opened in turn


@dataclass(frozen=True)
class Query:
    name: str
    call: Callable[[int], Any]  # given the call's number (to vary what it asks)
    whole_scan: bool = False


@dataclass(frozen=True)
class Scene:
    """A node over the filled catalog, with its clock at the fill's moment, and what queries ask for."""

    node: Node
    now: dt.datetime
    client: Any  # a TestClient on the REST app
    run_ids: list[str]  # sealed runs, for their pages
    entry: Tuid  # the scanned dataset's

    @classmethod
    @contextlib.contextmanager
    def open(cls, catalog: sessionmaker[Session], now: dt.datetime) -> Iterator[Scene]:
        with tempfile.TemporaryDirectory(prefix="fleet_scale_node_") as folder:
            node = _node(Path(folder), catalog, now)
            app = create_app(node)
            app.include_router(runs_rest.router)  # a node with ingest has them; this one serves reads only
            totals.count_job(catalog, now)  # as a running depot's job has (the overview reads its count)
            with session_scope(catalog) as session:
                run_ids = _sample_runs(session)
                entry = Tuid.parse(catalog_queries.dataset_entry_id(session, DATASET) or "")
            with warnings.catch_warnings():  # Starlette's: a test client on httpx is deprecated
                warnings.simplefilter("ignore")
                from fastapi.testclient import TestClient
            with TestClient(app) as client:
                freeze_startup_objects()  # as `fleet serve` does once started: later collections skip them
                yield cls(node, now, client, run_ids, entry)


def _node(folder: Path, catalog: sessionmaker[Session], now: dt.datetime) -> Node:
    settings = load_settings(data_dir=folder / "data", scheduler=False, auth="off")
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    return Node(
        settings=settings,
        catalog=catalog,
        tiers=Tiers(open_store((folder / "warm").as_uri()), open_store((folder / "cold").as_uri())),
        hot=HotStore(folder / "hot", durability=Durability.OFF, interval_ms=50, min_free_bytes=0),
        auth=open_auth(settings, catalog),
        default_robot=settings.default_robot,
        secret_fields=SecretFields(settings.secret_fields),
        clock=lambda: now,
    )


def _sample_runs(session: Session) -> list[str]:
    """Sealed runs spread over the fleet's history (every how-many-th run by id)."""
    total = session.scalar(sa.select(sa.func.count()).select_from(Run)) or 1
    step = max(1, total // RUN_PAGES)
    ranked = (
        sa.select(Run.id, sa.func.row_number().over(order_by=Run.id).label("n")).where(Run.tier != Tier.HOT).subquery()
    )
    picked = sa.select(ranked.c.id).where(ranked.c.n % step == 0)
    return list(session.scalars(picked.limit(RUN_PAGES))) or list(session.scalars(sa.select(Run.id).limit(1)))


def _runs(scene: Scene, **asked: Any) -> Callable[[int], Any]:
    return lambda _: runs_answer(scene.node.catalog, RunFilter(**asked))


def _second_page(scene: Scene, **asked: Any) -> Callable[[int], Any]:
    """The page after the first one, by the first one's cursor (asked once, as a client holds it)."""
    cursor = runs_answer(scene.node.catalog, RunFilter(**asked))["next_cursor"]
    return lambda _: runs_answer(scene.node.catalog, RunFilter(**asked, cursor=cursor))


def _scan(scene: Scene, whole: bool) -> Callable[[int], Any]:
    depot = Depot(scene.node, None)
    reader = Principal("bench", frozenset({Scope.READ}))

    def call(_: int) -> int:
        parts = segments.scan(depot, reader, scene.entry, cloud_pb2.ScanSegmentTableRequest())
        if not whole:
            next(parts)  # the rest is never read (a client that stops after the first part)
            return 1
        return sum(1 for _ in parts)

    return call


def _run_page(scene: Scene) -> Callable[[int], Any]:
    known = policies()
    return lambda n: run_answer(scene.node.catalog, scene.run_ids[n % len(scene.run_ids)], known)


def _runs_ls(scene: Scene) -> Callable[[int], Any]:
    """What `fleet runs ls --robot R` sends (sdk_client's `runs`: its defaults, sort and limit)."""

    def call(n: int) -> Any:
        params = {"robot": robot_name(n % ROBOTS), "sort": "-started_at", "limit": 100}
        answer = scene.client.get("/v1/runs", params=params)
        answer.raise_for_status()
        return answer.json()

    return call


def _count_totals(scene: Scene) -> Callable[[int], Any]:
    def call(_: int) -> Any:
        with session_scope(scene.node.catalog) as session:
            return totals.count(session)

    return call


def _retention_plan(scene: Scene) -> Callable[[int], Any]:
    ctx = Retention(node=scene.node, policies=policies())
    return lambda _: plan_answer(ctx, list(ACTIONS))


def queries(scene: Scene) -> list[Query]:
    week = (scene.now - dt.timedelta(days=60)).isoformat(), (scene.now - dt.timedelta(days=53)).isoformat()
    since, until = (dt.datetime.fromisoformat(t) for t in week)
    runs: list[tuple[str, dict[str, Any]]] = [
        ("GET /v1/runs (newest first)", {}),
        ("GET /v1/runs robot=robot-042", {"robot": ["robot-042"]}),
        ("GET /v1/runs application=inspection", {"application": ["inspection"]}),
        ("GET /v1/runs since..until (a week, 2 months ago)", {"since": since, "until": until}),
        ("GET /v1/runs status=live", {"status": "live"}),
        ("GET /v1/runs tier=warm", {"tier": "warm"}),
        ("GET /v1/runs property=fleet.site=site-3", {"properties": {"fleet.site": "site-3"}}),
        ("GET /v1/runs property=fleet.robot_id=robot-007", {"properties": {"fleet.robot_id": "robot-007"}}),
        ("GET /v1/runs metric=distance_m>2000", {"metric": ["distance_m>2000"]}),
        ("GET /v1/runs metric=interventions>=3", {"metric": ["interventions>=3"]}),
        ("GET /v1/runs tag=night-shift", {"tag": ["night-shift"]}),
        ("GET /v1/runs event=stuck", {"event": ["stuck"]}),
        ("GET /v1/runs sort=started_at", {"sort": "started_at"}),
        ("GET /v1/runs sort=-bytes", {"sort": "-bytes"}),
        ("GET /v1/runs sort=bytes", {"sort": "bytes"}),
        ("GET /v1/runs sort=id", {"sort": "id"}),
        ("GET /v1/runs sort=-id", {"sort": "-id"}),
        ("GET /v1/runs sort=-metric.distance_m", {"sort": "-metric.distance_m"}),
        ("GET /v1/runs sort=metric.distance_m", {"sort": "metric.distance_m"}),
    ]
    found = [Query(name, _runs(scene, **asked)) for name, asked in runs]
    found += [
        Query("GET /v1/runs second page (cursor)", _second_page(scene)),
        Query("GET /v1/runs sort=-metric.distance_m second page", _second_page(scene, sort="-metric.distance_m")),
        Query("GET /v1/runs/RUN (a run's page)", _run_page(scene)),
        Query("fleet runs ls --robot R (REST in-process)", _runs_ls(scene)),
        Query("redap ScanSegmentTable, first part", _scan(scene, whole=False)),
        Query("redap ScanSegmentTable, whole (a quarter of the runs)", _scan(scene, whole=True), whole_scan=True),
        Query("console overview", lambda _: fleet.overview(scene.node, None, now=scene.now)),
        Query("fleet totals job (once a minute)", _count_totals(scene)),
        Query("retention plan (every action)", _retention_plan(scene)),
    ]
    return found
