"""Scheduling: one retention job at a time across processes (a Postgres advisory lock, two real
`fleet serve` processes on one catalog), and promotion ahead of schedule past the hot high-water mark.

The hard limit (new data refused at FLEET_MIN_FREE_BYTES, HTTP 507) is proven by
tests/services/ingest/test_service.py::test_disk_guard_refuses_before_writing.
"""

from __future__ import annotations

import datetime as dt
import itertools
import subprocess
import sys
import threading
import uuid
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

import httpx
import pytest
import sqlalchemy as sa
from sqlalchemy.orm import Session

from catalog import queries
from catalog.db import create_engine, session_scope
from catalog.models import JobExecution
from services.ingest.service import IngestService
from services.retention.locks import job_lock
from services.retention.schedule import promote_job, retention_job
from services.retention.service import PROMOTE, plan
from services.rrd import iter_events
from services.sealed.tiers import Tiers
from services.storage.objectstore import open_store
from tests.postgres import temporary_database
from tests.services.ingest import feeding
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.retention.conftest import NodeFactory
from tests.services.rrd.recordings import Recording
from tests.waiting import wait_for

HOLDER = """
import sys, time
from catalog import queries
from catalog.db import create_engine, session_scope
from services.retention.locks import job_lock
with job_lock(create_engine(sys.argv[1]), sys.argv[2]) as got:
    print("HELD" if got else "BUSY", flush=True)
    time.sleep(600)  # until the test kills this process
"""


def _free(engine: sa.Engine, job: str) -> bool:
    with job_lock(engine, job) as got:
        return got


@contextmanager
def _held(engine: sa.Engine, job: str, timeout: float) -> Iterator[None]:
    """Hold the job's lock, taking it as soon as whoever has it lets go."""

    def taken() -> ExitStack | None:
        holding = ExitStack()
        if holding.enter_context(job_lock(engine, job)):
            return holding
        holding.close()
        return None

    with wait_for(taken, timeout, f"the {job} lock", interval=0.01):
        yield


# --- the lock itself ---------------------------------------------------------------------------


@pytest.mark.postgres
def test_postgres_lock_is_held_by_one_connection_at_a_time(postgres_url: str):
    one, other = create_engine(postgres_url), create_engine(postgres_url)  # two pools: as two processes
    job = f"test-{uuid.uuid4().hex[:8]}"
    try:
        with job_lock(one, job) as first:
            assert first is True
            assert _free(other, job) is False
            assert _free(one, job) is False  # another connection of the same pool is another holder
            assert _free(other, job + "-x") is True  # each job name has a lock of its own
        assert _free(other, job) is True
        assert _free(one, job) is True
    finally:
        one.dispose()
        other.dispose()


@pytest.mark.postgres
def test_postgres_lock_of_a_killed_process_is_freed(postgres_url: str):
    """A process that dies holding the lock frees it (its connection ends): the job is not stuck."""
    engine = create_engine(postgres_url)
    job = f"test-{uuid.uuid4().hex[:8]}"
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, postgres_url, job],
        stdout=subprocess.PIPE,
        text=True,
        cwd=Path(__file__).resolve().parents[3],
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "HELD"
        assert _free(engine, job) is False
        holder.kill()
        holder.wait(timeout=10)
        wait_for(lambda: _free(engine, job), 10, "the dead holder's lock to be released")
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
        engine.dispose()


def test_duckdb_lock_is_exclusive_within_the_process(tmp_path: Path):
    engine = create_engine(f"duckdb:///{tmp_path / 'a.duckdb'}")
    elsewhere = create_engine(f"duckdb:///{tmp_path / 'b.duckdb'}")
    seen: list[bool] = []
    with job_lock(engine, "retention") as first:
        assert first is True
        thread = threading.Thread(target=lambda: seen.append(_free(engine, "retention")))
        thread.start()
        thread.join(10)
        assert seen == [False]
        assert _free(engine, "retention") is False  # not re-entrant either
        assert _free(engine, "promote") is True
        assert _free(elsewhere, "retention") is True  # another catalog, another lock
    assert _free(engine, "retention") is True
    engine.dispose()
    elsewhere.dispose()


def test_retention_job_skips_while_another_holds_the_lock(make_node: NodeFactory, tmp_path: Path):
    node = make_node(Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri())))
    engine = node.catalog.kw["bind"]

    def job_rows() -> int:
        with Session(engine) as session:
            return int(session.scalar(sa.select(sa.func.count()).where(JobExecution.job == "retention")) or 0)

    with job_lock(engine, "retention") as got:
        assert got
        assert retention_job(node.retention) is None
        assert job_rows() == 0
    assert retention_job(node.retention) == []
    assert job_rows() == 1


# --- two real service processes on one Postgres catalog ----------------------------------------

SCENES_A, SCENES_B = ("points", "large", "scalars"), ("image", "textlogs", "transforms", "properties")
SKIPPED = "retention job is running in another process: skipped"


@pytest.fixture
def pg_catalog() -> Iterator[str]:
    with temporary_database("fleet_sched") as url:
        upgraded = subprocess.run(
            [FLEET, "db", "upgrade", "--catalog-url", url], capture_output=True, text=True, timeout=60
        )
        assert upgraded.returncode == 0, upgraded.stderr
        yield url


def _skips(server: LiveServer) -> int:
    return server.log.read_text().count(SKIPPED) if server.log.exists() else 0


def _overlapping(rows: list[JobExecution]) -> list[tuple[JobExecution, JobExecution]]:
    """Pairs of job runs that overlap in time (a run not finished lasts until the end)."""
    far = dt.datetime.max.replace(tzinfo=dt.UTC)
    spans = sorted(
        ((_aware(r.started_at), _aware(r.finished_at) if r.finished_at else far, r) for r in rows), key=lambda s: s[0]
    )
    return [(a[2], b[2]) for a, b in itertools.pairwise(spans) if b[0] < a[1]]


def _aware(value: dt.datetime) -> dt.datetime:
    return value if value.tzinfo else value.replace(tzinfo=dt.UTC)


@pytest.mark.slow
@pytest.mark.sdk
@pytest.mark.postgres
def test_two_processes_run_the_retention_job_one_at_a_time(
    pg_catalog: str, tmp_path: Path, recordings: dict[str, Recording]
):
    shared = {
        "catalog_url": pg_catalog,
        "warm_url": (tmp_path / "warm").as_uri(),
        "cold_url": (tmp_path / "cold").as_uri(),
        "promote_after_s": "0",
        "promote_interval_s": "0.3",
        "retention_interval_s": "0.3",
        "warm_days": "0",
        "cold_days": "365",
    }
    a = LiveServer(tmp_path / "a", **shared)
    b = LiveServer(tmp_path / "b", **shared)
    engine = create_engine(pg_catalog)
    try:
        a.start()
        b.start()
        runs = {}
        for server, scenes in ((a, SCENES_A), (b, SCENES_B)):
            for scene in scenes:
                answer = httpx.post(f"{server.url}/v1/uploads", content=recordings[scene].data, timeout=60)
                assert answer.status_code == 200, answer.text
                runs[recordings[scene].recordings[0]["recording_id"]] = server

        def tiers_now() -> set[str]:
            return {httpx.get(f"{a.url}/v1/runs/{run}", timeout=10).json()["tier"] for run in runs}

        # each node promotes its own runs; the retention job (one node or the other) archives them
        a.wait_for(lambda: tiers_now() == {"cold"}, timeout=60, what="every run promoted then archived")

        # a third holder of the lock (this test): both services skip their turns while it holds it
        before = {server: _skips(server) for server in (a, b)}
        with _held(engine, "retention", 10):
            held_from = dt.datetime.now(dt.UTC)
            wait_for(lambda: all(_skips(s) > before[s] for s in (a, b)), 20, "both services to skip a turn")
            held_to = dt.datetime.now(dt.UTC)
        # the services take turns again
        wait_for(lambda: _count(engine, held_to) >= 2, 20, "retention jobs after the lock was released")
        # both take turns: each has run the job (which one wins a turn is up to timing, so wait for it)
        assert a.proc is not None and b.proc is not None
        pids = {str(a.proc.pid), str(b.proc.pid)}
        wait_for(lambda: _nodes(engine) == pids, 60, "both services to have run the retention job")
        events = {
            run: [e["action"] for e in httpx.get(f"{a.url}/v1/runs/{run}", timeout=10).json()["events"]] for run in runs
        }
    finally:
        a.stop()
        b.stop()
    with Session(engine) as session:
        rows = list(session.scalars(sa.select(JobExecution).where(JobExecution.job == "retention")))
        promotions = list(session.scalars(sa.select(JobExecution).where(JobExecution.job == "promote")))
    engine.dispose()

    # Both services are stopped now: a job with no end was cut by its service's stop (which frees the
    # lock it held, so the other service may have run one after it); it ran nothing to the end.
    rows = [r for r in rows if r.finished_at is not None]
    nodes = {r.node.rsplit(":", 1)[1] for r in rows}  # hostname:pid
    assert nodes == pids, f"retention ran on {nodes}, the services are {pids}"
    overlaps = [
        [(r.node, _aware(r.started_at).isoformat(), r.finished_at and _aware(r.finished_at).isoformat()) for r in pair]
        for pair in _overlapping(rows)
    ]
    assert overlaps == [], "two retention jobs ran at the same time"
    assert not [
        r
        for r in rows
        if _aware(r.started_at) < held_to and (r.finished_at is None or _aware(r.finished_at) > held_from)
    ], "a job ran while the test held the lock"
    assert all(r.outcome == "ok" for r in rows), [r.detail for r in rows if r.outcome != "ok"]
    archived = sum(int(r.detail.split(" done")[0]) for r in rows)
    assert archived == len(runs)  # every run archived once, by one job or another
    for run, actions in events.items():
        assert actions.count("promote") == 1 and actions.count("archive") == 1, (run, actions)
    # promotion is each node's own: each promoted exactly the runs uploaded to it
    promoted = {
        pid: sum(int(r.detail.split(" done")[0]) for r in promotions if r.node.endswith(f":{pid}")) for pid in pids
    }
    assert promoted == {str(a.proc.pid): len(SCENES_A), str(b.proc.pid): len(SCENES_B)}


def _nodes(engine: sa.Engine) -> set[str]:
    """The processes (pids) that have run the retention job."""
    with Session(engine) as session:
        return {
            node.rsplit(":", 1)[1]
            for node in session.scalars(sa.select(JobExecution.node).where(JobExecution.job == "retention"))
        }


def _count(engine: sa.Engine, since: dt.datetime) -> int:
    with Session(engine) as session:
        return int(
            session.scalar(
                sa.select(sa.func.count()).where(JobExecution.job == "retention", JobExecution.started_at > since)
            )
            or 0
        )


# --- the hot high-water mark -------------------------------------------------------------------


def _upload(ingest: IngestService, path: Path) -> str:
    report = feeding.upload(ingest, iter_events(path))
    assert report.chunks_new > 0  # past the high-water mark data is still taken; only the hard limit refuses
    return report.runs[0]


@pytest.mark.sdk
def test_past_the_high_water_mark_closed_runs_are_promoted_oldest_first(
    make_node: NodeFactory, tmp_path: Path, recordings: dict[str, Recording]
):
    free = {"bytes": 10 << 30}
    tiers = Tiers(open_store((tmp_path / "warm").as_uri()), open_store((tmp_path / "cold").as_uri()))
    node = make_node(tiers, promote_after_s=600, promote_below_free_bytes=1 << 30, free_bytes=lambda: free["bytes"])
    start = node.clock.now
    order = {}
    # uploaded in one order, their last data in another: "oldest" is by last data
    for scene, minutes in (("points", 2), ("scalars", 0), ("textlogs", 1)):
        node.clock.now = start + dt.timedelta(minutes=minutes)
        order[minutes] = _upload(node.ingest, recordings[scene].path)
    oldest_first = [order[m] for m in sorted(order)]
    live = node.ingest.open_source(live=True)  # a run still being logged: never promoted early
    for event in iter_events(recordings["image"].path):
        node.ingest.accept(live, event)
    live_run = recordings["image"].recordings[0]["recording_id"]
    assert node.ingest.runs[live_run].status == "live"
    node.clock.now = start + dt.timedelta(minutes=3)

    assert plan(node.retention, [PROMOTE]) == []  # plenty of room: nothing before promote_after
    free["bytes"] = 512 << 20  # below the 1 GiB high-water mark
    actions = plan(node.retention, [PROMOTE])
    assert [a.run_id for a in actions] == oldest_first
    assert all(a.reason == "hot disk past its high-water mark: promoted ahead of schedule" for a in actions)

    outcomes = promote_job(node.retention)
    assert outcomes is not None and [o.action.run_id for o in outcomes] == oldest_first
    assert all(o.ok for o in outcomes), [o.detail for o in outcomes]
    assert set(node.ingest.runs) == {live_run}  # the live run stays hot
    assert plan(node.retention, [PROMOTE]) == []

    node.ingest.close_source(live)  # once closed and idle long enough it goes by the schedule
    node.clock.advance(minutes=11)
    free["bytes"] = 10 << 30
    (due,) = plan(node.retention, [PROMOTE])
    assert due.run_id == live_run and due.reason.startswith("closed and idle for")


def test_job_runs_older_than_the_history_are_forgotten(tiers: Tiers, make_node: NodeFactory):
    from services.retention.schedule import JOB_HISTORY

    node = make_node(tiers, promote_after_s=0)
    with session_scope(node.catalog) as session:
        queries.start_job(session, "retention", "old-node", node.clock() - JOB_HISTORY - dt.timedelta(hours=1))
        queries.start_job(session, "retention", "recent-node", node.clock() - JOB_HISTORY + dt.timedelta(hours=1))
    assert retention_job(node.retention) == []
    with session_scope(node.catalog) as session:
        nodes = sorted(j.node for j in queries.recent_jobs(session))
    assert "old-node" not in nodes and "recent-node" in nodes and len(nodes) == 2
