"""Promotion hot -> warm: a closed run sealed, uploaded, verified, switched in the catalog, removed.

Steps, each safe to repeat: (1) seal the hot file into `recording.rrd` + `chunks.parquet` in the
run's hot folder; (2) upload them, then `run.json`, under `ROBOT/YYYY-MM-DD/RUN/` (same keys every
time, so a retry overwrites rather than orphans); (3) check what the store holds against what was
sealed; (4) switch the catalog to warm in one transaction; (5) remove the hot files. A crash
before (4) leaves the run hot, and the next promotion redoes (1)-(3) over the same keys; a crash
after (4) leaves a hot copy whose chunks are all sealed, removed at the next start or promotion.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import shutil
from collections.abc import Iterator
from dataclasses import dataclass

from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.queries import ObjectRecord, RunRecord
from services.analytics.extract import Extractor
from services.analytics.store import write_analytics
from services.errors import ErrorCode, FleetError
from services.ingest.service import IngestService, RunState
from services.retention.seal import INDEX, RECORDING, RUN_JSON, SealedRun, seal
from services.retention.tiers import Tiers, run_json, run_prefix
from services.rrd.decoder import iter_events
from services.rrd.messages import Event
from services.runs.download import read_events
from services.storage.objectstore import RangeReader

log = logging.getLogger(__name__)

SEAL_DIR = "seal"
MAX_BACKOFF = dt.timedelta(minutes=5)


class PromotionDeferredError(FleetError):
    """New data reached the run while it was being sealed: it is promoted later, whole."""

    code = ErrorCode.CONFLICT


@dataclass(frozen=True)
class Candidate:
    run: RunState
    reason: str


def due_for_promotion(ingest: IngestService, now: dt.datetime, promote_after: dt.timedelta,
                      disk_pressure: bool) -> list[Candidate]:
    """Closed hot runs to promote, oldest first: idle for `promote_after`, or all of them under
    disk pressure (past the high-water mark). Runs backing off after a failure wait their turn."""
    out = []
    for run in sorted(list(ingest.runs.values()), key=lambda r: r.last_data_at):
        if run.status != "closed" or run.live_sources or run.sealed:
            continue
        if run.next_promote_at is not None and now < run.next_promote_at:
            continue
        idle = now - run.last_data_at
        if idle >= promote_after:
            out.append(Candidate(run, f"closed and idle for {_human(idle)} (promote after {_human(promote_after)})"))
        elif disk_pressure:
            out.append(Candidate(run, "hot disk past its high-water mark: promoted ahead of schedule"))
    return out


def _human(delta: dt.timedelta) -> str:
    seconds = int(delta.total_seconds())
    return f"{seconds // 3600}h{seconds // 60 % 60:02d}m" if seconds >= 3600 else f"{seconds // 60}m{seconds % 60:02d}s"


def promote(run: RunState, ingest: IngestService, tiers: Tiers, catalog: sessionmaker[Session],
            now: dt.datetime) -> RunRecord:
    """Seal `run` into the warm tier; returns its new catalog record. On failure the run stays hot
    and backs off (1 s, 2 s, 4 s ... up to 5 minutes) before the next attempt."""
    try:
        record = _promote(run, ingest, tiers, catalog, now)
    except Exception:
        run.promote_failures += 1
        wait = min(dt.timedelta(seconds=2 ** (run.promote_failures - 1)), MAX_BACKOFF)
        run.next_promote_at = now + wait
        raise
    return record


def _promote(run: RunState, ingest: IngestService, tiers: Tiers, catalog: sessionmaker[Session],
             now: dt.datetime) -> RunRecord:
    size = run.hot.size
    workdir = run.hot.directory / SEAL_DIR
    workdir.mkdir(exist_ok=True)
    sealed_as = run.sealed_as
    prefix = sealed_as.prefix if sealed_as else None
    sources: list[Iterator[Event | None]] = []
    if prefix is not None:  # chunks that came after the run was sealed: sealed in with the rest
        base = workdir / "base.rrd"
        _download(tiers, f"{prefix}/{RECORDING}", base)
        sources.append(iter(iter_events(base)))
    sources.append(read_events(run.hot.path, size, None))
    analytics = Extractor(run.run_id)
    sealed = seal(sources, workdir / RECORDING, run.run_id, now, analytics.add)  # (1)
    record = _sealed_record(run, sealed, ingest.default_robot)
    prefix = prefix or run_prefix(record.robot_id, record.date, run.run_id)
    objects = [ObjectRecord(RECORDING, f"{prefix}/{RECORDING}", "warm", sealed.recording_size,
                            sealed.recording_sha256),
               ObjectRecord(INDEX, f"{prefix}/{INDEX}", "warm", len(sealed.index), sealed.index_sha256)]
    with open(sealed.recording, "rb") as fh:  # (2) checked by the store against what was sent
        tiers.warm.put(objects[0].key, fh)
    tiers.warm.put(objects[1].key, sealed.index)
    objects += write_analytics(tiers.warm, analytics, record.robot_id, record.date.isoformat())
    tiers.warm.put(f"{prefix}/{RUN_JSON}", run_json(record, prefix, objects, now))
    for obj in objects:  # (3)
        held = tiers.warm.head(obj.key).size
        if held != obj.size:
            raise FleetError(f"{tiers.warm.url}/{obj.key} holds {held} bytes after upload, {obj.size} were sealed")
    with run.sealing:  # ingest waits here only if it has data for this very run
        if run.hot.size != size or run.status == "live":
            raise PromotionDeferredError(f"run {run.run_id} received data while being sealed: promoted later")
        detail = f"{sealed.recording_size} bytes, {len(sealed.chunk_ids)} chunks to {tiers.warm.url}/{prefix}/"
        with session_scope(catalog) as session:  # (4)
            queries.record_promotion(session, record, prefix, objects, now, detail)
        run.sealed = True
        ingest.forget(run)
    shutil.rmtree(run.hot.directory, ignore_errors=True)  # (5)
    log.info("promoted run %s: %s", run.run_id, detail)
    return record


def _sealed_record(run: RunState, sealed: SealedRun, default_robot: str) -> RunRecord:
    """The run's catalog record after sealing: identity as it was filed, figures from the sealed file."""
    filed = run.record(default_robot)
    figures = sealed.facts.record(default_robot)
    if run.sealed_as is not None:
        filed.robot_id, filed.date = run.sealed_as.robot_id, run.sealed_as.date
    return dataclasses.replace(
        filed, status="closed", tier="warm", sdk_version=figures.sdk_version or filed.sdk_version,
        chunks=figures.chunks, rows=figures.rows, bytes=figures.bytes, properties=figures.properties,
        entities=figures.entities, timelines=figures.timelines, ended_at=filed.ended_at or run.last_data_at,
        started_at=figures.started_at or filed.started_at)


def _download(tiers: Tiers, key: str, path: object) -> None:
    size = tiers.warm.head(key).size
    reader = RangeReader(tiers.warm, key, size)
    with open(str(path), "wb") as out:
        while piece := reader.read(8 * 1024 * 1024):
            out.write(piece)
