"""Promotion hot -> warm: a closed run sealed, uploaded, verified, switched in the catalog, removed.

Steps, each safe to repeat: (1) seal the hot file into `recording.rrd` + `chunks.parquet`, and (2)
upload them under `ROBOT/YYYY-MM-DD/RUN/` (same keys every time, so a retry overwrites rather than
orphans): the recording is sealed straight into the store as it is made, without a local copy
(`services/sealed/upload.py`), and the store keeps it only once whole; (3) check what the store
holds against what was sealed; (4) switch the catalog to warm in one transaction, which puts
`run.json` (built from the rows it wrote) before it commits; (5) remove the hot files. A crash
before (4) commits leaves the run hot, and the next promotion redoes (1)-(3) over the same keys; a
crash after (4) leaves a hot copy whose chunks are all sealed, which its next promotion finds so and
removes without sealing again (so does a late upload that brought nothing new).
Whether a run was sealed before is asked of the catalog here, not at ingest: ingest files data even
while the catalog does not answer.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from sqlalchemy.orm import Session

from catalog import queries
from catalog.db import session_scope
from catalog.queries import ObjectRecord, RunRecord
from core.backoff import backoff_delay
from core.errors import ConflictError, InsufficientStorageError
from core.states import RunStatus, Tier
from services.analytics.extract import Extractor
from services.analytics.store import write_analytics
from services.cluster.ownership import Lease
from services.facts.sealed import SealedInfo
from services.hot.read import read_events
from services.ingest.service import IngestService
from services.ingest.view import HotRunView
from services.lakehouse.sync import copy_now
from services.node import Node
from services.rrd.decoder import iter_events
from services.rrd.messages import Event
from services.sealed.tiers import Tiers, run_prefix, write_run_json
from services.sealed.upload import seal_to_store
from services.sealed.write import INDEX, RECORDING, SealedRun
from services.storage.objectstore import RangeReader, StorageError

log = logging.getLogger(__name__)

SEAL_DIR = "seal"
FIRST_BACKOFF = dt.timedelta(seconds=1)
MAX_BACKOFF = dt.timedelta(minutes=5)
# Told a run's id once its seal has committed (wired by the server: the corpus evaluates the run).
OnSealed = Callable[[str], None]
PROMOTING = threading.Lock()  # one promotion at a time in this process (scheduled pass or asked for)


@dataclass
class PromoteBackoff:
    """Failed promotions of this node's hot runs, by run id: how many in a row, and when the next
    attempt may start (1 s, 2 s, 4 s ... up to MAX_BACKOFF). Kept by retention, not on ingest's runs:
    a run that is sealed at last is forgotten here, so data that comes later starts afresh."""

    failures: dict[str, int] = field(default_factory=dict)
    retry_at: dict[str, dt.datetime] = field(default_factory=dict)

    def waiting(self, run_id: str, now: dt.datetime) -> dt.datetime | None:
        """When the run may be tried again, if that is still to come."""
        at = self.retry_at.get(run_id)
        return at if at is not None and now < at else None

    def failed(self, run_id: str, now: dt.datetime) -> None:
        failures = self.failures[run_id] = self.failures.get(run_id, 0) + 1
        wait = backoff_delay(failures, first=FIRST_BACKOFF.total_seconds(), cap=MAX_BACKOFF.total_seconds())
        self.retry_at[run_id] = now + dt.timedelta(seconds=wait)

    def forget(self, run_id: str) -> None:
        self.failures.pop(run_id, None)
        self.retry_at.pop(run_id, None)


@dataclass(frozen=True)
class Candidate:
    run: HotRunView
    reason: str


def due_for_promotion(
    ingest: IngestService,
    node: Node,
    now: dt.datetime,
    promote_after: dt.timedelta,
    disk_pressure: bool,
    backoff: PromoteBackoff,
) -> list[Candidate]:
    """Closed hot runs to promote, oldest first: idle for `promote_after`, or all of them under
    disk pressure (past the high-water mark). Runs backing off after a failure wait their turn."""
    out = []
    for run in ingest.closed_runs():
        if backoff.waiting(run.run_id, now) is not None:
            continue
        if node.ownership is not None and run.lease is None:
            continue  # another node owns it, or the catalog has not said: the ownership pass settles it
        idle = now - run.last_data_at
        if idle >= promote_after:
            out.append(Candidate(run, f"closed and idle for {_human(idle)} (promote after {_human(promote_after)})"))
        elif disk_pressure:
            out.append(Candidate(run, "hot disk past its high-water mark: promoted ahead of schedule"))
    return out


Upcoming = tuple[HotRunView, dt.datetime | None, str]


def upcoming(
    ingest: IngestService, now: dt.datetime, promote_after: dt.timedelta, backoff: PromoteBackoff
) -> list[Upcoming]:
    """Hot runs not due yet: when each will be promoted (None: once it closes), and why."""
    out: list[Upcoming] = []
    for run in ingest.hot_runs():
        retry_at = backoff.waiting(run.run_id, now)
        if run.status == RunStatus.LIVE or run.live_sources:
            out.append(
                (
                    run,
                    None,
                    f"live: promoted {_human(promote_after)} after its stream closes "
                    "(or FLEET_CLOSE_AFTER_S after its last data)",
                )
            )
        elif retry_at is not None:
            out.append((run, retry_at, f"retrying after {backoff.failures[run.run_id]} failed attempts"))
        elif now - run.last_data_at < promote_after:
            out.append(
                (
                    run,
                    run.last_data_at + promote_after,
                    f"closed, idle {_human(now - run.last_data_at)} of {_human(promote_after)}",
                )
            )
    return out


def _human(delta: dt.timedelta) -> str:
    seconds = int(delta.total_seconds())
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


def promote(
    run: HotRunView,
    ingest: IngestService,
    node: Node,
    now: dt.datetime,
    reserve_bytes: int = 0,
    backoff: PromoteBackoff | None = None,
    actor: str = "retention",
    on_sealed: OnSealed | None = None,
) -> RunRecord | None:
    """Seal `run` into the warm tier; returns its new catalog record (None when the run held nothing
    that was not sealed already: its hot copy is simply removed). On failure the run stays hot and,
    given a `backoff`, waits there (1 s, 2 s, 4 s ... up to 5 minutes) before the next attempt.
    `actor` names who asked, for the run's events: "retention" when the schedule did. `run` is as
    ingest gave it just before: data it received since makes the hand-over refuse (promoted later).
    `on_sealed` is told the run's id once its seal has committed (what rules make of the run); its
    failure is logged, never the promotion's."""
    try:
        record = _promote(run, ingest, node, now, reserve_bytes, actor)
    except Exception:
        if backoff is not None:
            if ingest.has_left(run):  # what failed came after the catalog switch
                backoff.forget(run.run_id)
            else:
                backoff.failed(run.run_id, now)
        raise
    if backoff is not None:
        backoff.forget(run.run_id)
    if record is not None and on_sealed is not None:
        _tell_sealed(on_sealed, run.run_id)
    return record


def _tell_sealed(on_sealed: OnSealed, run_id: str) -> None:
    try:
        on_sealed(run_id)
    except Exception:  # the seal stands; what depends on it catches up later (the rules backfill)
        log.exception("run %s was sealed, but what follows a seal failed", run_id)


def _promote(
    run: HotRunView,
    ingest: IngestService,
    node: Node,
    now: dt.datetime,
    reserve_bytes: int,
    actor: str,
) -> RunRecord | None:
    adds_to = _sealed_before(run, ingest)
    if adds_to is not None and run.chunk_ids <= adds_to.chunk_ids:
        _drop_hot_copy(run, ingest, node, adds_to, f"all {len(run.chunk_ids)} of its chunks are sealed already")
        return None
    workdir = run.directory / SEAL_DIR
    try:
        return _seal_and_switch(run, ingest, node, now, reserve_bytes, adds_to, workdir, actor)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)  # a failed attempt leaves nothing on the hot disk


def _sealed_before(run: HotRunView, ingest: IngestService) -> SealedInfo | None:
    """Whether the run was sealed before (its hot data came later): asked of the catalog now, as ingest
    may have filed the data while the catalog did not answer, or another node may have sealed it."""
    sealed = ingest.sealed_lookup(run.run_id) if ingest.sealed_lookup is not None else run.adds_to
    if sealed is not None and sealed.tier != Tier.WARM:
        what = (
            "restore it (fleet runs restore), then it is sealed in"
            if sealed.tier == Tier.COLD
            else "it was deleted: its late data stays hot until removed by hand"
        )
        raise ConflictError(f"run {run.run_id} received {len(run.chunk_ids)} chunks while {sealed.tier}: {what}")
    ingest.set_adds_to(run, sealed)
    return sealed


def _drop_hot_copy(run: HotRunView, ingest: IngestService, node: Node, adds_to: SealedInfo, why: str) -> None:
    """A hot copy with nothing the sealed run lacks: removed, and the data that follows is filed
    beside the sealed run (`adds_to`, where its chunks are)."""
    left = ingest.hand_over(run, lambda _: adds_to, doing="being checked", then="promoted later")
    shutil.rmtree(left.folder, ignore_errors=True)
    if node.ownership is not None and left.lease is not None:
        node.ownership.release(left.lease)
    log.info("hot copy of run %s removed: %s", run.run_id, why)


def _check_room(run: HotRunView, tiers: Tiers, base_size: int, reserve_bytes: int) -> None:
    """Sealing late data downloads the sealed recording to the hot disk first, and a warm store that
    is a folder on that disk takes the new recording there: refuse before starting rather than fill
    the disk the catalog lives on. (An S3 warm store takes the sealed recording as it is made.)"""
    need = base_size
    warm_root = getattr(tiers.warm, "root", None)
    if (
        isinstance(warm_root, Path)
        and warm_root.exists()
        and os.stat(warm_root).st_dev == os.stat(run.directory).st_dev
    ):
        need += run.size + base_size
    free = shutil.disk_usage(run.directory).free
    if free - need < reserve_bytes:
        raise InsufficientStorageError(
            f"sealing run {run.run_id} needs about {need} bytes on the hot disk, which has {free} free and keeps "
            f"{reserve_bytes} in reserve (FLEET_RESERVE_BYTES): free space, or use an s3:// warm store"
        )


def _seal_and_switch(
    run: HotRunView,
    ingest: IngestService,
    node: Node,
    now: dt.datetime,
    reserve_bytes: int,
    adds_to: SealedInfo | None,
    workdir: Path,
    actor: str,
) -> RunRecord:
    tiers, catalog = node.tiers, node.catalog
    took = _Stopwatch()
    prefix = adds_to.prefix if adds_to else None
    base_size = tiers.warm.head(f"{prefix}/{RECORDING}").size if prefix is not None else 0
    _check_room(run, tiers, base_size, reserve_bytes)
    workdir.mkdir(exist_ok=True)
    sources: list[Iterator[Event]] = []
    if prefix is not None:  # chunks that came after the run was sealed: sealed in with the rest
        base = workdir / "base.rrd"
        download_warm(tiers, f"{prefix}/{RECORDING}", base)
        sources.append(iter(iter_events(base)))
    sources.append(read_events(run.path, run.size))
    analytics = Extractor(run.run_id, spill_dir=workdir)  # written to files there as the rows come
    filed = run.record(node.default_robot)  # sealing keeps the robot and date the run was filed under
    prefix = prefix or run_prefix(filed.robot_id, filed.date, run.run_id)
    # (1) and (2): sealed straight into the store, the upload with checksums the store verifies
    sealed = seal_to_store(
        tiers.warm, f"{prefix}/{RECORDING}", sources, run.run_id, now, analytics.add, node.secret_fields
    )
    took.lap("sealed")
    record = _sealed_record(run, adds_to, sealed, node.default_robot)
    objects = [
        ObjectRecord(RECORDING, f"{prefix}/{RECORDING}", Tier.WARM, sealed.recording_size, sealed.recording_sha256),
        ObjectRecord(INDEX, f"{prefix}/{INDEX}", Tier.WARM, len(sealed.index), sealed.index_sha256),
    ]
    tiers.warm.put(objects[1].key, sealed.index)
    objects += write_analytics(tiers.warm, analytics.files(), run.run_id, record.robot_id, record.date.isoformat())
    for obj in objects:  # (3)
        held = tiers.warm.head(obj.key).size
        if held != obj.size:
            raise StorageError(f"{tiers.warm.url}/{obj.key} holds {held} bytes after upload, {obj.size} were sealed")
    took.lap("index and analytics")
    detail = f"{sealed.recording_size} bytes, {len(sealed.chunk_ids)} chunks to {tiers.warm.url}/{prefix}/"
    stale: set[str] = set()

    def switch(lease: Lease | None) -> SealedInfo:  # (4), under the run's lock
        with session_scope(catalog, write=True) as session:
            _give_up_lease(session, run.run_id, lease, ingest, node)
            stale.update(queries.analytics_keys(session, run.run_id) - {o.key for o in objects})
            queries.record_promotion(session, record, prefix, objects, now, detail, actor)
            write_run_json(session, tiers.warm, run.run_id)  # with the pin as the catalog has it now
        return SealedInfo(Tier.WARM, prefix, record.robot_id, record.date, frozenset(sealed.chunk_ids))

    left = ingest.hand_over(run, switch, doing="being sealed", then="promoted later")
    took.lap("catalog")
    for key in stale:  # analytics written earlier under another robot or date: one copy per run
        tiers.warm.delete(key)
    shutil.rmtree(left.folder, ignore_errors=True)  # (5)
    took.lap("hot copy removed")
    copy_now(node.lakehouse, catalog, tiers.warm, node.clock, [run.run_id])  # its rows in the Iceberg tables
    took.lap("lakehouse")
    log.info("promoted run %s: %s (%s)", run.run_id, detail, took)
    return record


class _Stopwatch:
    """How long each step of a promotion took, for its log line."""

    def __init__(self) -> None:
        self._last = time.perf_counter()
        self._laps: list[tuple[str, float]] = []

    def lap(self, step: str) -> None:
        now = time.perf_counter()
        self._laps.append((step, now - self._last))
        self._last = now

    def __str__(self) -> str:
        return ", ".join(f"{step} {seconds:.2f} s" for step, seconds in self._laps)


def _give_up_lease(session: Session, run_id: str, lease: Lease | None, ingest: IngestService, node: Node) -> None:
    """Many nodes on one catalog: only the run's owner seals it, and gives the run up in the same
    transaction (a node that lost the run meanwhile hands its hot copy over instead)."""
    ownership = node.ownership
    if ownership is None:
        return
    if lease is None or not ownership.holds(session, lease):
        ingest.lose_lease(run_id)
        raise ConflictError(f"run {run_id} is owned by another node now: its hot copy here is handed over to it")
    ownership.release_in(session, lease)


def _sealed_record(run: HotRunView, adds_to: SealedInfo | None, sealed: SealedRun, default_robot: str) -> RunRecord:
    """The run's catalog record after sealing: identity as it was filed (the sealed run's, for data
    that `adds_to` it), figures from the sealed file."""
    filed = run.record(default_robot)
    figures = sealed.facts.record(default_robot)
    return dataclasses.replace(
        filed,
        robot_id=adds_to.robot_id if adds_to is not None else filed.robot_id,
        date=adds_to.date if adds_to is not None else filed.date,
        status=RunStatus.CLOSED,
        tier=Tier.WARM,
        sdk_version=figures.sdk_version or filed.sdk_version,
        chunks=figures.chunks,
        rows=figures.rows,
        bytes=figures.bytes,
        properties=figures.properties,
        entities=figures.entities,
        timelines=figures.timelines,
        ended_at=filed.ended_at or run.last_data_at,
        started_at=figures.started_at or filed.started_at,
    )


def download_warm(tiers: Tiers, key: str, path: object) -> None:
    """A warm object copied to a local file, in pieces (a sealed recording may be many GB)."""
    size = tiers.warm.head(key).size
    reader = RangeReader(tiers.warm, key, size)
    with open(str(path), "wb") as out:
        while piece := reader.read(8 * 1024 * 1024):
            out.write(piece)
