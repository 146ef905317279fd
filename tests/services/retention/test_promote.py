"""Promotion hot -> warm, over a local-folder and an S3 (moto) warm store: a closed run idle for
`promote_after` is sealed into recording.rrd + chunks.parquet + run.json, uploaded, verified,
switched to warm in the catalog in one transaction, and its hot files removed. Every step is made
to fail in turn (a fault-injecting store wrapper, a failing catalog switch, a crash before the hot
files go); the next run of the job completes with no lost chunk and no orphaned object."""

from __future__ import annotations

import datetime as dt
import hashlib
import io
import itertools
import json
import logging
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import pytest
import sqlalchemy as sa

from catalog import queries
from catalog.db import session_scope
from services.facts.identity import SecretFields
from services.ingest.view import HotRunView
from services.retention import promote
from services.retention.rebuild import rebuild
from services.retention.schedule import promote_job
from services.retention.service import PROMOTE, Outcome, plan, run_plan, set_pinned
from services.rrd import ArrowMessage, iter_events
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.decoder import decode_message
from services.rrd.frames import MESSAGE_HEADER_SIZE, STREAM_HEADER_SIZE, decode_message_header
from services.rrd.messages import EndMessage, StreamFooter
from services.runs import download, sealed
from services.sealed.index import CHUNK, IndexRow, from_parquet
from services.sealed.read import locate_sealed
from services.sealed.tiers import Tiers, parse_run_json
from services.sealed.write import INDEX, RECORDING, RUN_JSON
from services.storage.objectstore import ObjectInfo, ObjectStore, StorageError, Uploads, open_store
from tests.services.ingest import feeding
from tests.services.retention.conftest import Clock, Node, NodeFactory, listing, log_run
from tests.services.rrd.recordings import rerun_rrd_ok
from tests.services.runs import decoded

pytestmark = pytest.mark.sdk

RUN, ROBOT = "promote-run-1", "robot-7"
PROMOTE_AFTER_S = 600.0
FIRST_BACKOFF_S = 1.0  # after a first failure
FILE_ONLY = pytest.mark.parametrize("tiers", ["file"], indirect=True)  # what no store behaviour changes


@dataclass(frozen=True)
class SdkRuns:
    first: Path  # the run as the robot logged it
    later: Path  # more chunks of the same recording id, logged later (late data)


@pytest.fixture(scope="module")
def sdk_runs(tmp_path_factory: pytest.TempPathFactory) -> SdkRuns:
    folder = tmp_path_factory.mktemp("promote-runs")
    with pytest.MonkeyPatch.context() as env, ThreadPoolExecutor(2) as pool:  # one SDK process each, side by side
        env.setenv("RERUN_FLUSH_NUM_ROWS", "4")  # the SDK's batcher: chunks of at most 4 frames (several per entity)
        first = pool.submit(log_run, folder / "first.rrd", RUN, entities=4, frames=10, points=200, robot=ROBOT)
        later = pool.submit(
            log_run, folder / "later.rrd", RUN, entities=3, frames=4, points=100, robot=ROBOT, text=False
        )
        return SdkRuns(first.result(), later.result())


# --- helpers -------------------------------------------------------------------------------------


def promote_now(node: Node) -> list[Outcome]:
    return run_plan(node.retention, plan(node.retention, [PROMOTE]))


def metas(source: Path | bytes) -> list[ChunkMeta]:
    """Every chunk of a recording, in file order (duplicates kept)."""
    events = iter_events(io.BytesIO(source) if isinstance(source, bytes) else source)
    return [chunk_meta(e) for e in events if isinstance(e, ArrowMessage)]


def chunk_ids(source: Path | bytes) -> list[bytes]:
    return [m.chunk_id for m in metas(source)]


def served(node: Node, run_id: str) -> bytes:
    """The whole run as GET /v1/runs/RUN/recording.rrd answers it, from whichever tier holds it."""
    everything = download.EntityFilter()
    hot = node.ingest.hot_recording(run_id)
    if hot is not None:
        return b"".join(decoded.stream_run(hot.path, hot.size, everything))
    found = locate_sealed(node.catalog, node.tiers.warm, run_id, node.clock())
    return b"".join(sealed.stream_sealed(found, everything))


def hot_dir(node: Node, run_id: str = RUN) -> Path:
    return node.root / "hot" / run_id


def catalog_tier(node: Node, run_id: str = RUN) -> str:
    with session_scope(node.catalog) as session:
        run = queries.get_run(session, run_id)
        assert run is not None
        return run.tier


def assert_warm(node: Node, want: set[bytes], run_id: str = RUN) -> tuple[str, bytes, list[IndexRow]]:
    """The run is sealed as promised: catalog warm with what the store holds (sizes and SHA-256),
    exactly three objects under its prefix, nothing in the store the catalog does not account for,
    every chunk once, no hot copy left. Returns the prefix, the recording and its index."""
    with session_scope(node.catalog) as session:
        run = queries.get_run(session, run_id)
        life = queries.lifecycle(session, run_id)
        assert run is not None and life is not None
        assert run.tier == "warm"
        prefix, date = life.prefix, run.date
        figures = (
            run.robot_id,
            run.date,
            run.application_id,
            run.chunks,
            run.rows,
            run.bytes,
            run.pinned,
            sorted(e.path for e in queries.run_entities(session, run_id)),
            sorted((t.name, t.min, t.max) for t in queries.run_timelines(session, run_id)),
        )
        recorded = {name: (o.key, o.size, o.sha256, o.tier) for name, o in queries.run_objects(session, run_id).items()}
    assert prefix == f"{ROBOT}/{date.isoformat()}/{run_id}"
    under = [info.key for info in node.tiers.warm.list(prefix + "/")]
    assert under == [f"{prefix}/{name}" for name in (INDEX, RECORDING, RUN_JSON)]
    # No orphan: every object in the store is one the catalog records, or the run's run.json.
    assert sorted(listing(node.tiers.warm)) == sorted([key for key, *_ in recorded.values()] + [f"{prefix}/{RUN_JSON}"])
    assert {RECORDING, INDEX} <= set(recorded)
    for name, (key, size, sha256, tier) in recorded.items():
        data = node.tiers.warm.get_range(key)
        assert (len(data), hashlib.sha256(data).hexdigest(), tier) == (size, sha256, "warm"), name
    assert recorded[RECORDING][0] == f"{prefix}/{RECORDING}" and recorded[INDEX][0] == f"{prefix}/{INDEX}"
    recording = node.tiers.warm.get_range(f"{prefix}/{RECORDING}")
    ids = chunk_ids(recording)
    assert len(ids) == len(set(ids)) and set(ids) == want  # every chunk, once
    rows = from_parquet(node.tiers.warm.get_range(f"{prefix}/{INDEX}"))
    assert sorted(r.chunk_id for r in rows if r.kind == CHUNK) == sorted(want)  # type: ignore[type-var]
    run_file = parse_run_json(node.tiers.warm.get_range(f"{prefix}/{RUN_JSON}"))  # the catalog record, beside it
    record = run_file.record
    assert (run_file.prefix, record.id, record.tier) == (prefix, run_id, "warm")
    assert (
        record.robot_id,
        record.date,
        record.application_id,
        record.chunks,
        record.rows,
        record.bytes,
        run_file.pinned,
        sorted(e.path for e in record.entities),
        sorted((t.name, t.min, t.max) for t in record.timelines),
    ) == figures
    assert record.bytes == len(recording)
    assert {o.name: (o.key, o.size, o.sha256, o.tier) for o in run_file.objects} == recorded
    assert not hot_dir(node, run_id).exists()
    assert run_id not in node.ingest.runs
    return prefix, recording, rows


# --- promotion -----------------------------------------------------------------------------------


def test_a_closed_run_is_sealed_once_idle_for_promote_after(
    tiers: Tiers,
    make_node: NodeFactory,
    sdk_runs: SdkRuns,
    rerun_bin: str,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
):
    caplog.set_level(logging.INFO, logger="services.retention.promote")
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
    report = node.upload(sdk_runs.first)
    original = metas(sdk_runs.first)
    assert report.chunks_new == len(original) and report.chunks_duplicate == 0

    clock.advance(seconds=PROMOTE_AFTER_S - 1)
    assert plan(node.retention, [PROMOTE]) == []  # not before promote_after
    assert catalog_tier(node) == "hot" and listing(tiers.warm) == []
    clock.advance(seconds=2)
    (action,) = plan(node.retention, [PROMOTE])
    assert (action.run_id, action.action, action.robot_id, action.tier) == (RUN, PROMOTE, ROBOT, "hot")
    assert "closed and idle for 10m01s" in action.reason
    outcomes = promote_job(node.retention, wait=True)
    assert outcomes is not None and [o.ok for o in outcomes] == [True], outcomes
    (logged,) = [r.getMessage() for r in caplog.records if r.getMessage().startswith(f"promoted run {RUN}:")]
    steps = "sealed", "index and analytics", "catalog", "hot copy removed", "lakehouse"  # what took the time
    assert re.search(", ".join(rf"{step} \d+\.\d\d s" for step in steps) + r"\)$", logged), logged
    with session_scope(node.catalog) as session:
        (job,) = queries.recent_jobs(session)
        assert (job.job, job.outcome) == ("promote", "ok")
        assert [e.action for e in queries.run_events(session, RUN)] == ["promote"]
        run = queries.get_run(session, RUN)
        assert run is not None
        assert run.chunks == len(original)

    _, recording, rows = assert_warm(node, {m.chunk_id for m in original})
    with session_scope(node.catalog) as session:  # the text logs went to the analytics tables
        assert set(queries.run_objects(session, RUN)) == {RECORDING, INDEX, "analytics/text_logs"}
    assert plan(node.retention, [PROMOTE]) == []  # promoted once

    # recording.rrd: one stream with a footer, the run as the SDK wrote it.
    out = tmp_path / "recording.rrd"
    out.write_bytes(recording)
    rerun_rrd_ok(rerun_bin, "verify", str(out))
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", str(sdk_runs.first), str(out))
    events = list(iter_events(io.BytesIO(recording)))
    (end,) = [e for e in events if isinstance(e, EndMessage)]
    assert isinstance(events[-1], StreamFooter) and end.footer is not None
    assert [m.store_id.recording_id for m in end.footer.manifests] == [RUN]  # the manifest of its one store
    assert {e.stream_index for e in events} == {0}  # one stream
    assert served(node, RUN) == recording  # a whole download is the sealed object

    # chunks.parquet: one row per message, back to back; each chunk row's byte range is that chunk.
    truth = {m.chunk_id: m for m in original}
    assert rows[0].offset == STREAM_HEADER_SIZE
    assert all(b.offset == a.end for a, b in itertools.pairwise(rows))
    chunk_rows = [r for r in rows if r.kind == CHUNK]
    assert len(chunk_rows) == len(truth)
    for row in chunk_rows:
        frame = recording[row.offset : row.end]
        kind, length = decode_message_header(frame)
        assert MESSAGE_HEADER_SIZE + length == row.length
        meta = chunk_meta(decode_message(kind, frame[MESSAGE_HEADER_SIZE:], row.offset))  # type: ignore[arg-type]
        assert row.chunk_id is not None
        want = truth[row.chunk_id]
        assert meta.chunk_id == row.chunk_id
        assert (row.entity_path, row.is_static, row.num_rows) == (want.entity_path, want.is_static, want.num_rows)
        assert row.store_kind == "recording"
        assert {(t.name, t.type, t.min, t.max) for t in row.timelines} == {
            (t.name, t.type, t.range.min, t.range.max) for t in want.timelines
        }
    static = [r for r in chunk_rows if r.entity_path == "/world/static"]
    assert len(static) == 1 and static[0].is_static and static[0].timelines == ()
    frames = sorted(
        (t.min, t.max) for r in chunk_rows if r.entity_path == "/world/e0" for t in r.timelines if t.name == "frame"
    )
    assert len(frames) > 1 and frames[0][0] == 0 and frames[-1][1] == 9  # split by the batcher; frames 0-9 logged
    assert all(a[1] < b[0] for a, b in itertools.pairwise(frames))


@FILE_ONLY
def test_a_live_run_is_never_promoted(tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns):
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=0, promote_below_free_bytes=1 << 60, free_bytes=lambda: 0)
    source = node.ingest.open_source(live=True)
    for event in iter_events(sdk_runs.first):
        node.ingest.accept(source, event)
    clock.advance(days=30)
    assert plan(node.retention, [PROMOTE]) == []  # not when idle, not under disk pressure
    assert promote_job(node.retention, wait=True) == []
    node.ingest.close_source(source)  # the stream ends: the run closes and is due at once
    (action,) = plan(node.retention, [PROMOTE])
    assert action.run_id == RUN
    assert [o.ok for o in promote_now(node)] == [True]
    assert_warm(node, set(chunk_ids(sdk_runs.first)))


# --- a failure at each step, then the next run of the job -----------------------------------------


class FaultyStore:
    """The warm store with an injected fault: the next `times` calls of `op` ("put" or "head") on a
    key containing `name` raise StorageError, before reaching the store or, with `after`, once the
    store did the work (the answer lost on the way back)."""

    def __init__(self, inner: ObjectStore, op: str, name: str, *, after: bool = False, times: int = 1) -> None:
        self.inner, self.url = inner, inner.url
        self.op, self.name, self.after, self.left = op, name, after, times

    def _fault(self, op: str, key: str, after: bool) -> None:
        if self.left and (op, after) == (self.op, self.after) and self.name in key:
            self.left -= 1
            raise StorageError(f"injected fault: {op} {key} ({'after' if after else 'before'} the store)")

    def put(self, key: str, data: bytes | BinaryIO) -> ObjectInfo:
        self._fault("put", key, False)
        info = self.inner.put(key, data)
        self._fault("put", key, True)
        return info

    def head(self, key: str) -> ObjectInfo:
        self._fault("head", key, False)
        return self.inner.head(key)

    def get_range(self, key: str, start: int = 0, length: int | None = None) -> bytes:
        return self.inner.get_range(key, start, length)

    def list(self, prefix: str = "") -> Iterator[ObjectInfo]:
        return self.inner.list(prefix)

    def delete(self, key: str) -> None:
        self.inner.delete(key)


# Each step fails in turn (tiers, op, key, after the store did it, next run on a restarted node).
# The wrapper is the same over both stores: every step runs over the folder, a few over S3 (moto).
STEPS = [
    ("put", RECORDING, False, False, "put-recording"),
    ("put", RECORDING, True, True, "put-recording-answer-lost-restart"),
    ("put", INDEX, False, False, "put-index"),
    ("put", INDEX, True, True, "put-index-answer-lost-restart"),
    ("put", "analytics/", False, False, "put-analytics"),
    ("put", "analytics/", True, True, "put-analytics-answer-lost-restart"),
    ("put", RUN_JSON, False, True, "put-run-json-restart"),
    ("put", RUN_JSON, True, False, "put-run-json-answer-lost"),
    ("head", RECORDING, False, False, "verify-recording"),
    ("head", INDEX, False, True, "verify-index-restart"),
]
ON_S3 = ("put-recording-answer-lost-restart", "put-index", "verify-index-restart")
FAULTS = [
    pytest.param(tier, *step[:4], id=f"{tier}-{step[4]}")
    for tier in ("file", "s3-moto")
    for step in STEPS
    if tier == "file" or step[4] in ON_S3
]


def hot_run(node: Node) -> HotRunView:
    """The run as ingest hands it to promotion now."""
    run = node.ingest.hot_run(RUN)
    assert run is not None
    return run


def assert_still_hot(node: Node, want: set[bytes]) -> None:
    """A failed promotion left the run hot, whole and served; the catalog untouched."""
    with session_scope(node.catalog) as session:
        run = queries.get_run(session, RUN)
        assert run is not None and run.tier == "hot"
        assert queries.lifecycle(session, RUN) is None and queries.run_objects(session, RUN) == {}
        assert queries.run_events(session, RUN) == []
    assert not node.ingest.runs[RUN].handed_over and (hot_dir(node) / "run.rrd").is_file()
    ids = chunk_ids(served(node, RUN))
    assert len(ids) == len(set(ids)) and set(ids) == want  # no chunk lost


def retry(node: Node, make_node: NodeFactory, tiers: Tiers, clock: Clock, restart: bool) -> Node:
    """The next run of the job: on the same node once the backoff is over, or after a restart."""
    clock.advance(seconds=FIRST_BACKOFF_S)
    if restart:
        node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
        # a recovered run is idle from its file's mtime, wall time: on a busy machine later than
        # this clock's start by more than the backoff
        clock.advance(seconds=PROMOTE_AFTER_S)
    outcomes = promote_now(node)
    assert [(o.action.run_id, o.ok) for o in outcomes] == [(RUN, True)], outcomes
    return node


@pytest.mark.parametrize(("tiers", "op", "name", "after", "restart"), FAULTS, indirect=["tiers"])
def test_a_failed_step_leaves_a_state_the_next_run_completes(
    tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns, op: str, name: str, after: bool, restart: bool
):
    clock = Clock()
    faulty = FaultyStore(tiers.warm, op, name, after=after)
    node = make_node(Tiers(faulty, tiers.cold), clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    want = set(chunk_ids(sdk_runs.first))
    clock.advance(seconds=PROMOTE_AFTER_S)
    (outcome,) = promote_now(node)
    assert not outcome.ok and "injected fault" in outcome.detail and faulty.left == 0
    assert_still_hot(node, want)

    node = retry(node, make_node, tiers if restart else node.tiers, clock, restart)
    prefix, recording, _ = assert_warm(node, want)
    assert plan(node.retention, [PROMOTE]) == []
    assert served(node, RUN) == recording == tiers.warm.get_range(f"{prefix}/{RECORDING}")


@FILE_ONLY
@pytest.mark.parametrize("restart", [False, True], ids=["same-node", "restarted"])
def test_a_failed_catalog_switch_changes_nothing_in_the_catalog(
    tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns, monkeypatch: pytest.MonkeyPatch, restart: bool
):
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    want = set(chunk_ids(sdk_runs.first))
    record_promotion = queries.record_promotion

    def fails_at_commit(session, *args, **kwargs):  # everything written, then the transaction fails
        record_promotion(session, *args, **kwargs)
        session.flush()
        raise RuntimeError("injected fault: the catalog went away before the commit")

    monkeypatch.setattr(queries, "record_promotion", fails_at_commit)
    clock.advance(seconds=PROMOTE_AFTER_S)
    (outcome,) = promote_now(node)
    assert not outcome.ok and "injected fault" in outcome.detail
    assert_still_hot(node, want)  # one transaction: no warm tier, no lifecycle, no objects, no event
    monkeypatch.undo()

    node = retry(node, make_node, tiers, clock, restart)
    assert_warm(node, want)


def test_a_crash_before_the_hot_files_go_is_finished_at_restart(
    tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns, rerun_bin: str, tmp_path: Path
):
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    want = set(chunk_ids(sdk_runs.first))
    clock.advance(seconds=PROMOTE_AFTER_S)
    with pytest.MonkeyPatch.context() as crash:  # the process dies right after the catalog switch
        crash.setattr(shutil, "rmtree", lambda *args, **kwargs: None)  # the module promote removes them with
        assert [o.ok for o in promote_now(node)] == [True]
    assert catalog_tier(node) == "warm"
    assert not hot_dir(node).exists()  # set aside at once: a new hot run of the same id may start
    (aside,) = [d for d in (node.root / "hot").iterdir() if d.name.startswith(".")]
    assert (aside / "run.rrd").is_file()
    assert set(chunk_ids(served(node, RUN))) == want  # served from the warm tier meanwhile

    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)  # restart: the set-aside copy goes
    assert not aside.exists() and RUN not in node.ingest.runs
    assert plan(node.retention, [PROMOTE]) == []
    _, recording, _ = assert_warm(node, want)
    out = tmp_path / "recording.rrd"
    out.write_bytes(recording)
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", str(sdk_runs.first), str(out))


def test_a_crash_right_after_the_switch_leaves_a_hot_copy_removed_without_sealing_again(
    tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns
):
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    want = set(chunk_ids(sdk_runs.first))
    clock.advance(seconds=PROMOTE_AFTER_S)

    def crash(*_: object) -> None:
        raise SystemExit("killed")

    with pytest.MonkeyPatch.context() as patch, pytest.raises(SystemExit):
        patch.setattr(node.ingest.hot, "set_aside", crash)
        promote.promote(hot_run(node), node.ingest, node.context, clock.now)
    assert catalog_tier(node) == "warm" and (hot_dir(node) / "run.rrd").is_file()
    with session_scope(node.catalog) as session:
        life = queries.lifecycle(session, RUN)
        assert life is not None
        sealed_before = node.tiers.warm.head(f"{life.prefix}/{RECORDING}")
    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)  # restart: recovered as hot
    clock.advance(seconds=PROMOTE_AFTER_S)
    (outcome,) = promote_now(node)
    assert outcome.ok and outcome.detail.startswith("nothing new"), outcome.detail
    assert not hot_dir(node).exists() and RUN not in node.ingest.runs
    prefix, _, _ = assert_warm(node, want)
    after = node.tiers.warm.head(f"{prefix}/{RECORDING}")
    assert (after.etag, after.last_modified) == (sealed_before.etag, sealed_before.last_modified)  # not sealed again
    with session_scope(node.catalog) as session:
        assert [e.action for e in queries.run_events(session, RUN)] == ["promote"]


# --- backoff -------------------------------------------------------------------------------------


@FILE_ONLY
def test_a_failed_promotion_backs_off_before_the_next_attempt(tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns):
    clock = Clock()
    faulty = FaultyStore(tiers.warm, "put", RECORDING, times=3)
    node = make_node(Tiers(faulty, tiers.cold), clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    run = hot_run(node)
    backoff = node.retention.promote_backoff
    assert backoff.retry_at.get(RUN) is None
    clock.advance(seconds=PROMOTE_AFTER_S)
    for failures, wait in ((1, FIRST_BACKOFF_S), (2, 2.0), (3, 4.0)):  # 1 s, 2 s, 4 s ...
        failed_at = clock.now
        (outcome,) = promote_now(node)
        assert not outcome.ok
        assert backoff.failures[RUN] == failures and backoff.retry_at[RUN] == failed_at + dt.timedelta(seconds=wait)
        clock.advance(seconds=wait - 0.1)
        assert plan(node.retention, [PROMOTE]) == []  # skipped until its retry time
        clock.advance(seconds=0.1)
        assert [a.run_id for a in plan(node.retention, [PROMOTE])] == [RUN]

    backoff.failures[RUN], faulty.left = 30, 1  # ... up to five minutes
    with pytest.raises(StorageError):
        promote.promote(run, node.ingest, node.context, clock.now, backoff=backoff)
    assert backoff.retry_at[RUN] == clock.now + promote.MAX_BACKOFF == clock.now + dt.timedelta(minutes=5)
    clock.advance(minutes=5)
    assert [o.ok for o in promote_now(node)] == [True]
    assert_warm(node, set(chunk_ids(sdk_runs.first)))
    assert RUN not in backoff.failures and RUN not in backoff.retry_at  # sealed: data that follows starts afresh


# --- late data -----------------------------------------------------------------------------------


def test_late_data_is_sealed_in_with_the_rest(
    tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns, rerun_bin: str, tmp_path: Path
):
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    first, later = chunk_ids(sdk_runs.first), chunk_ids(sdk_runs.later)
    assert not set(first) & set(later)
    clock.advance(seconds=PROMOTE_AFTER_S)
    assert [o.ok for o in promote_now(node)] == [True]
    prefix, _, _ = assert_warm(node, set(first))

    again = node.upload(sdk_runs.first)  # the same file once more: nothing new
    assert (again.chunks_new, again.chunks_duplicate) == (0, len(first))
    added = node.upload(sdk_runs.later)  # the same recording id, new chunks: an addendum, hot
    assert (added.runs, added.chunks_new, added.chunks_duplicate) == ([RUN], len(later), 0)
    addendum = node.ingest.runs[RUN]
    assert addendum.adds_to is not None and addendum.adds_to.prefix == prefix
    assert catalog_tier(node) == "warm"  # the sealed run stands until it is sealed again

    clock.advance(seconds=PROMOTE_AFTER_S)
    assert [a.run_id for a in plan(node.retention, [PROMOTE])] == [RUN]
    assert [o.ok for o in promote_now(node)] == [True]
    again_prefix, recording, _ = assert_warm(node, set(first) | set(later))  # the union, each chunk once
    assert again_prefix == prefix
    with session_scope(node.catalog) as session:
        run = queries.get_run(session, RUN)
        assert run is not None and run.chunks == len(first) + len(later)
        assert [e.action for e in queries.run_events(session, RUN)] == ["promote", "promote"]
    both = tmp_path / "both.rrd"  # the two SDK files one after the other: every chunk of both
    both.write_bytes(sdk_runs.first.read_bytes() + sdk_runs.later.read_bytes())
    out = tmp_path / "recording.rrd"
    out.write_bytes(recording)
    rerun_rrd_ok(rerun_bin, "verify", str(out))
    rerun_rrd_ok(rerun_bin, "compare", "--unordered", str(both), str(out))
    assert served(node, RUN) == recording

    assert node.upload(sdk_runs.later).chunks_duplicate == len(later)  # late data is now sealed too


@FILE_ONLY
def test_chunks_already_held_change_nothing_and_seal_nothing(tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns):
    """A robot's file copy uploaded again, or `rerun URL` pointed at the depot replaying a run, bring
    no new chunk: no hot run, no re-seal, and the run's facts (end, last data) stay as they were."""
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    clock.advance(seconds=PROMOTE_AFTER_S)
    assert [o.ok for o in promote_now(node)] == [True]
    facts = _facts(node)
    clock.advance(hours=2)
    first = chunk_ids(sdk_runs.first)
    again = node.upload(sdk_runs.first)
    assert (again.chunks_new, again.chunks_duplicate) == (0, len(first))
    live = node.ingest.open_source(live=True)  # a replay over gRPC, as `rerun URL` streams it back
    feeding.feed(node.ingest, live, iter_events(sdk_runs.first))
    node.ingest.close_source(live)
    node.ingest.flush_catalog()
    assert RUN not in node.ingest.runs and not hot_dir(node).exists()
    assert plan(node.retention, [PROMOTE]) == []  # nothing to seal again
    assert _facts(node) == facts
    with session_scope(node.catalog) as session:
        assert [e.action for e in queries.run_events(session, RUN)] == ["promote"]


def test_a_replay_into_a_hot_run_changes_none_of_its_facts(tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns):
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    facts = _facts(node)
    clock.advance(minutes=5)
    live = node.ingest.open_source(live=True)
    feeding.feed(node.ingest, live, iter_events(sdk_runs.first))
    assert node.ingest.runs[RUN].status == "closed"  # a stream of chunks already held is not a live run
    node.ingest.close_source(live)
    node.ingest.flush_catalog()
    assert _facts(node) == facts


def _facts(node: Node) -> tuple[object, ...]:
    with session_scope(node.catalog) as session:
        run = queries.get_run(session, RUN)
        assert run is not None
        return run.status, run.ended_at, run.last_data_at, run.chunks, run.tier


def test_sealing_reads_properties_with_the_nodes_secret_fields(tiers: Tiers, make_node: NodeFactory, tmp_path: Path):
    """A node that strips only passwords keeps an `api_key` field through promotion too (sealing reads
    the stored property chunks with the node's setting, not the default list; the fleet property's
    `token`, the depot's own credential, is stripped whatever the setting)."""
    node = make_node(tiers, clock=Clock(), secret_fields=SecretFields(["password"]))
    path = tmp_path / "props.rrd"
    subprocess.run(
        [
            sys.executable,
            "-c",
            f"""
import rerun as rr
rec = rr.RecordingStream("nav", recording_id="props-run")
rec.save({str(path)!r})
rec.send_property("fleet", rr.AnyValues(robot_id="robot-7", api_key="kept", token="hidden", password="hidden"))
rec.set_time("frame", sequence=0)
rec.log("/x", rr.Scalars(1.0))
rec.flush()
""",
        ],
        check=True,
        timeout=120,
        capture_output=True,
    )
    node.upload(path)
    node.ingest.flush_catalog()

    def fleet_property() -> dict[str, object]:
        with session_scope(node.catalog) as session:
            run = queries.get_run(session, "props-run")
            assert run is not None
            return dict(json.loads(run.properties)["fleet"])

    assert fleet_property() == {"robot_id": "robot-7", "api_key": "kept"}
    node.clock.advance(seconds=PROMOTE_AFTER_S)
    assert [o.ok for o in promote_now(node)] == [True]
    assert fleet_property() == {"robot_id": "robot-7", "api_key": "kept"}


def test_a_pin_set_while_hot_survives_promotion_and_a_rebuild(tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns):
    clock = Clock()
    node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    assert set_pinned(node.retention, RUN, True, "bob@lab")["pinned"] is True  # while hot
    clock.advance(seconds=PROMOTE_AFTER_S)
    assert [o.ok for o in promote_now(node)] == [True]
    prefix, _, _ = assert_warm(node, set(chunk_ids(sdk_runs.first)))
    run_file = parse_run_json(node.tiers.warm.get_range(f"{prefix}/{RUN_JSON}"))
    assert (run_file.pinned, run_file.pinned_by) == (True, "bob@lab")

    with session_scope(node.catalog, write=True) as session:  # the catalog is lost
        for table in ("runs", "run_lifecycle", "run_objects", "run_entities", "run_timelines", "retention_events"):
            session.execute(sa.text(f"DELETE FROM {table}"))
    rebuild(node.catalog, node.tiers, clock.now)
    with session_scope(node.catalog) as session:
        assert queries.pin_state(session, RUN) == (True, "bob@lab")


@FILE_ONLY
@pytest.mark.parametrize(
    ("op", "name", "restart"),
    [("put", INDEX, False), ("put", RUN_JSON, True), ("head", INDEX, True)],
    ids=["put-index", "put-run-json-restart", "verify-index-restart"],
)
def test_a_failed_late_data_promotion_is_completed(
    tiers: Tiers, make_node: NodeFactory, sdk_runs: SdkRuns, op: str, name: str, restart: bool
):
    """Sealing late data rewrites the run's objects in place: a failure after the merged recording
    is uploaded leaves it beside an index and a catalog that may be the old ones. The run is served
    whole meanwhile, and the next run of the job (after a restart too) records what the store holds."""
    clock = Clock()
    faulty = FaultyStore(tiers.warm, op, name, times=0)
    node = make_node(Tiers(faulty, tiers.cold), clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(sdk_runs.first)
    first, later = set(chunk_ids(sdk_runs.first)), set(chunk_ids(sdk_runs.later))
    clock.advance(seconds=PROMOTE_AFTER_S)
    assert [o.ok for o in promote_now(node)] == [True]
    node.upload(sdk_runs.later)
    clock.advance(seconds=PROMOTE_AFTER_S)
    faulty.left = 1
    (outcome,) = promote_now(node)
    assert not outcome.ok and "injected fault" in outcome.detail
    assert catalog_tier(node) == "warm"
    found = locate_sealed(node.catalog, tiers.warm, RUN, clock.now)
    whole = chunk_ids(b"".join(sealed.stream_sealed(found, download.EntityFilter())))
    assert first <= set(whole) and len(whole) == len(set(whole))
    for entity in ("/world/e0", "/world/static"):  # ranged reads planned from the index
        part = metas(b"".join(sealed.stream_sealed(found, download.EntityFilter([entity]))))
        assert {m.chunk_id for m in part} >= {m.chunk_id for m in metas(sdk_runs.first) if m.entity_path == entity}

    if restart:
        node = make_node(tiers, clock=clock, promote_after_s=PROMOTE_AFTER_S)
        assert RUN in node.ingest.runs, "the late data's hot copy was dropped at restart, its sealing never recorded"
    node = retry(node, make_node, tiers, clock, restart=False)
    assert_warm(node, first | later)


# --- multipart uploads ---------------------------------------------------------------------------


@pytest.mark.parametrize("tiers", ["s3-moto"], indirect=True)
def test_a_large_recording_is_uploaded_in_parts_and_checked(
    tiers: Tiers, make_node: NodeFactory, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
):
    part = 5 * 1024 * 1024  # S3's smallest part: a 14 MB run takes 3
    warm = open_store(
        tiers.warm.url, region="us-east-1", uploads=Uploads(part_bytes=part, concurrency=2), loop_reads=False
    )
    original = log_run(tmp_path / "large.rrd", RUN, entities=4, frames=10, points=30000, robot=ROBOT, text=False)
    clock = Clock()
    node = make_node(Tiers(warm, tiers.cold), clock=clock, promote_after_s=PROMOTE_AFTER_S)
    node.upload(original)
    clock.advance(seconds=PROMOTE_AFTER_S)
    assert [o.ok for o in promote_now(node)] == [True]
    prefix, recording, _ = assert_warm(node, set(chunk_ids(original)))
    etag = warm.head(f"{prefix}/{RECORDING}").etag
    assert etag is not None and etag.endswith(f"-{-(-len(recording) // part)}")  # one MD5 per part
