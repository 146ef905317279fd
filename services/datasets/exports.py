"""Export jobs: a snapshot version written as a LeRobot dataset by the depot, into a store it may
write (`FLEET_EXPORT_URLS`), with progress in the catalog.

A job is queued by `create` (`POST /v1/exports`), run by the one schedule (`run_due`, off the event
loop): it is claimed by one depot process, which beats a heartbeat every few seconds with its
progress, writes the episodes into a staging folder under the data dir (the LeRobot writer,
resumable), then puts the files into the target. A process killed midway leaves the job running
with a stale heartbeat: the next pass, on any process, claims it again and resumes after the last
written episode (the staging folder is on the node that ran it: another node starts it over). A
strict job checks every episode first and fails naming the flagged ones. A cancel is seen at the
next heartbeat.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import secrets
import shutil
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from catalog import dataset_exports as jobs
from catalog import datasets as queries
from catalog.db import session_scope
from catalog.models import DatasetExport
from core.clock import iso_utc
from core.errors import BadParameterError, ConflictError, FleetError, NotFoundError
from services.datasets.episodes import export_version, version_row
from services.datasets.export import ExportSpec, Progress, refuse_flagged
from services.datasets.lerobot.writer import PROGRESS_DIR
from services.datasets.quality import Limits
from services.datasets.resolve import Sources
from services.datasets.service import parse_ref
from services.settings import Settings
from services.storage.objectstore import check_key, open_store

log = logging.getLogger(__name__)

JOB = "dataset-exports"
STALE_S = 60.0  # a running job whose heartbeat is older was left by a process that died
BEAT_S = 5.0
FORMATS = ("lerobot",)
MAX_LIMIT = 200


@dataclass(frozen=True)
class Places:
    """Where the depot may write exports (`export_urls`), where it stages them, how it opens S3."""

    allowed: tuple[str, ...]
    staging: Path
    endpoint_url: str | None = None
    region: str | None = None

    @classmethod
    def of(cls, settings: Settings) -> Places:
        return cls(
            tuple(settings.export_urls), settings.data_dir / "exports", settings.s3_endpoint_url, settings.s3_region
        )


@dataclass(frozen=True)
class ExportRequest:
    name: str
    version: int
    format: str
    target: str
    spec: ExportSpec
    limits: Limits
    strict: bool

    def spec_json(self) -> str:
        return json.dumps({**self.spec.as_json(), **self.limits.as_json(), "strict": self.strict}, sort_keys=True)


def parse_version(ref: str) -> tuple[str, int]:
    """`NAME@N` as (name, number); a 422 naming the form otherwise."""
    name, number = parse_ref(ref)
    if number is None:
        raise BadParameterError("dataset", f"{ref[:80]!r}: name a version, NAME@N (`fleet datasets show {name}`)")
    return name, number


def check_target(target: str, allowed: tuple[str, ...]) -> str:
    """The target as the depot writes it: one of the allowed URLs or under one; a 422 otherwise."""
    parsed = urlparse(target)
    if parsed.scheme not in ("file", "s3") or parsed.query or parsed.fragment or ".." in parsed.path.split("/"):
        raise BadParameterError("to", f"{target[:200]!r}: the depot writes to file:///PATH or s3://BUCKET/PREFIX")
    wanted = target.rstrip("/")
    for place in allowed:
        base = place.rstrip("/")
        if wanted == base or wanted.startswith(base + "/"):
            return wanted
    if not allowed:
        raise BadParameterError(
            "to",
            "this depot writes no export (FLEET_EXPORT_URLS is not set): export to a folder of your own with "
            "`fleet datasets export NAME@N --to DIR`, or ask an admin to allow a place",
        )
    raise BadParameterError("to", f"{target[:200]!r} is not under a place this depot writes: {', '.join(allowed)}")


def default_fps(selection: dict[str, Any]) -> int:
    """The snapshot's rate (its selection's `fps`) as whole frames per second (10 if it named none)."""
    fps = selection.get("fps")
    if fps is None:
        return 10
    if float(fps) != int(fps):
        raise BadParameterError("fps", f"the snapshot's rate is {fps}: give a whole --fps for the export")
    return int(fps)


def create(sources: Sources, places: Places, request: ExportRequest, who: str) -> dict[str, Any]:
    """Queue the export; its job."""
    if request.format not in FORMATS:
        raise BadParameterError("format", f"{request.format!r}: one of {', '.join(FORMATS)}")
    request.spec.check()
    target = check_target(request.target, places.allowed)
    total, _ = version_row(sources, request.name, request.version)
    now = sources.clock()
    row = DatasetExport(
        id="exp-" + secrets.token_hex(6),
        name=request.name,
        version=request.version,
        format=request.format,
        spec=request.spec_json(),
        target=target,
        state=jobs.QUEUED,
        episodes=total,
        done=0,
        frames=0,
        skipped=0,
        flagged=0,
        bytes=0,
        report="[]",
        error=None,
        created_by=who,
        created_at=now,
        updated_at=now,
    )
    with session_scope(sources.catalog, write=True) as session:
        return job_json(jobs.add(session, row))


def job_json(row: DatasetExport) -> dict[str, Any]:
    return {
        "id": row.id,
        "dataset": queries.ref(row.name, row.version),
        "name": row.name,
        "version": row.version,
        "format": row.format,
        "to": row.target,
        "spec": json.loads(row.spec),
        "state": row.state,
        "episodes": row.episodes,
        "done": row.done,
        "frames": row.frames,
        "skipped": row.skipped,
        "flagged": row.flagged,
        "bytes": row.bytes,
        "percent": round(100.0 * row.done / row.episodes, 1) if row.episodes else 100.0,
        "report": json.loads(row.report),
        "error": row.error,
        "created_by": row.created_by,
        "created_at": iso_utc(row.created_at),
        "updated_at": iso_utc(row.updated_at),
    }


def job_answer(sources: Sources, job_id: str) -> dict[str, Any]:
    with session_scope(sources.catalog) as session:
        row = jobs.get(session, job_id)
        if row is None:
            raise NotFoundError(f"no export {job_id[:64]!r}: `fleet datasets exports` lists them")
        return job_json(row)


def jobs_answer(sources: Sources, dataset: str | None, limit: int) -> dict[str, Any]:
    if not 1 <= limit <= MAX_LIMIT:
        raise BadParameterError("limit", f"{limit}: 1 to {MAX_LIMIT}")
    name, version = (None, None)
    if dataset:
        name, version = parse_ref(dataset)
    with session_scope(sources.catalog) as session:
        return {"exports": [job_json(r) for r in jobs.listed(session, name, version, limit)]}


def cancel(sources: Sources, job_id: str) -> dict[str, Any]:
    with session_scope(sources.catalog, write=True) as session:
        row = jobs.get(session, job_id)
        if row is None:
            raise NotFoundError(f"no export {job_id[:64]!r}: `fleet datasets exports` lists them")
        if not jobs.cancel(session, job_id, sources.clock()):
            raise ConflictError(f"export {job_id} is {row.state}: only a queued or running export can be cancelled")
        session.refresh(row)
        return job_json(row)


def run_due(sources: Sources, places: Places, node: str) -> str | None:
    """Claim the oldest due export and run it to its end; its id (None: none due)."""
    stale = sources.clock() - dt.timedelta(seconds=STALE_S)
    with session_scope(sources.catalog) as session:
        due = jobs.due(session, stale)
    for job_id in due:
        with session_scope(sources.catalog, write=True) as session:
            if not jobs.claim(session, job_id, node, sources.clock(), stale):
                continue  # another process took it
            row = jobs.get(session, job_id)
            assert row is not None
            session.expunge(row)
        _Run(sources, places, row, node).run()
        return job_id
    return None


class _Stopped(Exception):
    """The job was cancelled, or taken over by another process."""


class _Run:
    def __init__(self, sources: Sources, places: Places, row: DatasetExport, node: str) -> None:
        self.sources, self.places, self.row, self.node = sources, places, row, node
        self.staging = places.staging / row.id
        self.progress: Progress | None = None
        self.reports: dict[int, dict[str, Any]] = {}
        self.written = 0
        self.state: str | None = jobs.RUNNING
        self.lock = threading.Lock()
        self.stop = threading.Event()

    def run(self) -> None:
        beating = threading.Thread(target=self._beat_every, name=f"export-{self.row.id}", daemon=True)
        beating.start()
        try:
            self._export()
            self._beat()
            self._end(jobs.DONE, None)
            shutil.rmtree(self.staging, ignore_errors=True)
            log.info(
                "export %s of %s@%s done: %d episodes", self.row.id, self.row.name, self.row.version, self.row.episodes
            )
        except _Stopped:
            if self.state == jobs.CANCELLED:
                shutil.rmtree(self.staging, ignore_errors=True)
            log.info("export %s stopped: %s", self.row.id, self.state or "taken over by another process")
        except FleetError as exc:
            self._beat()  # the episodes' report so far: why they could not be exported
            self._end(jobs.FAILED, str(exc))
        except Exception as exc:  # logged whole; the job says what kind of failure it was
            log.exception("export %s failed", self.row.id)
            self._end(jobs.FAILED, f"{type(exc).__name__}: see the depot's log")
        finally:
            self.stop.set()
            beating.join()

    def _export(self) -> None:
        options = json.loads(self.row.spec)
        spec, limits = ExportSpec.from_json(options), Limits.from_json(options)
        if options["strict"]:
            checked = export_version(self.sources, self.row.name, self.row.version, spec, None, self._seen, limits)
            refuse_flagged(checked.reports)
        export_version(self.sources, self.row.name, self.row.version, spec, self.staging, self._seen, limits)
        self._upload()

    def _seen(self, progress: Progress) -> None:
        with self.lock:
            self.progress = progress
            if progress.last is not None and (progress.last.flags or progress.last.exported_as is None):
                self.reports[progress.last.episode] = progress.last.as_json()
        if self.stop.is_set() or self.state != jobs.RUNNING:
            raise _Stopped

    def _upload(self) -> None:
        """The staged files into the target (meta/ last, so a reader never finds info.json first)."""
        store = open_store(self.row.target, endpoint_url=self.places.endpoint_url, region=self.places.region)
        staged = [p.relative_to(self.staging) for p in self.staging.rglob("*") if p.is_file()]
        kept = [p for p in staged if p.parts[0] != PROGRESS_DIR]
        files = sorted(kept, key=lambda p: (p.parts[0] == "meta", str(p)))
        for relative in files:
            if self.state != jobs.RUNNING:
                raise _Stopped
            path = self.staging / relative
            with path.open("rb") as data:
                store.put(check_key(relative.as_posix()), data)
            with self.lock:
                self.written += path.stat().st_size

    def _beat_every(self) -> None:
        while not self.stop.wait(BEAT_S):
            try:
                self._beat()
            except Exception:  # a catalog outage: the next beat tries again
                log.warning("export %s: heartbeat failed", self.row.id, exc_info=True)

    def _beat(self) -> None:
        with self.lock:
            seen = self.progress
            progress = jobs.Progress(
                seen.done if seen else 0,
                seen.frames if seen else 0,
                seen.skipped if seen else 0,
                seen.flagged if seen else 0,
                self.written,
                json.dumps([self.reports[k] for k in sorted(self.reports)]),
            )
        with session_scope(self.sources.catalog, write=True) as session:
            self.state = jobs.beat(session, self.row.id, self.node, self.sources.clock(), progress)

    def _end(self, state: str, error: str | None) -> None:
        with session_scope(self.sources.catalog, write=True) as session:
            jobs.end(session, self.row.id, self.node, state, self.sources.clock(), error)
        if error is not None:
            log.warning("export %s failed: %s", self.row.id, error)
