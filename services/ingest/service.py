"""Ingest: messages from live gRPC streams and from uploads, filed into runs, each chunk once.

A *source* is one gRPC `WriteMessages` stream or one upload. Its SetStoreInfo messages name the
recordings it carries; each recording is a run (run id = recording id). Blueprint stores are
kept with the recording they arrive beside. A chunk whose id the run already holds (sent live,
then uploaded from the FileSink copy) is counted as a duplicate and not written again.
"""

from __future__ import annotations

import datetime as dt
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy.orm import Session, sessionmaker

from catalog import queries
from catalog.db import session_scope
from catalog.queries import EntityRecord, RunRecord, TimelineRecord
from services.errors import ErrorCode, FleetError
from services.ingest.hot import HotRun, HotStore
from services.ingest.identity import (
    IDENTITY_PROPERTY,
    ROBOT_FIELD,
    START_TIME_COMPONENT,
    SecretFields,
    check_id,
    is_property_entity,
    read_property_chunk,
    run_date,
)
from services.ingest.replay import ReplayHub
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.frames import DEFAULT_VERSION, MessageKind, RerunVersion
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    Buffer,
    Event,
    StoreId,
    StoreInfoMessage,
    StoreKind,
    StreamStart,
)
from services.rrd.summary import StoreSummary
from services.rrd.validate import check_chunk

log = logging.getLogger(__name__)

LOG_TIME = "log_time"
_PENDING_LIMIT = 64 * 1024 * 1024


class InvalidStreamError(FleetError):
    code = ErrorCode.INVALID_ARGUMENT


class TooManyStreamsError(FleetError):
    code = ErrorCode.RESOURCE_EXHAUSTED


class SealedRunError(FleetError):
    code = ErrorCode.CONFLICT


@dataclass(frozen=True)
class SealedInfo:
    """What the catalog knows of a run that left the hot tier (given by the retention side)."""

    tier: str  # warm | cold | deleted
    prefix: str  # ROBOT/YYYY-MM-DD/RUN
    robot_id: str
    date: dt.date
    chunk_ids: frozenset[bytes]


SealedLookup = Callable[[str], SealedInfo | None]


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


@dataclass
class IngestReport:
    """What a source brought: the runs it touched and the chunks that were new or already held."""

    runs: list[str] = field(default_factory=list)
    chunks_new: int = 0
    chunks_duplicate: int = 0
    bytes_new: int = 0
    messages: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {"runs": self.runs, "chunks_new": self.chunks_new, "chunks_duplicate": self.chunks_duplicate,
                "bytes_new": self.bytes_new, "messages": self.messages}


@dataclass
class Source:
    live: bool  # a gRPC stream (its runs are live while it lasts) rather than an upload
    version: RerunVersion | None = None
    run_of_store: dict[StoreId, str] = field(default_factory=dict)
    recording_run: str | None = None  # where this source's blueprints go
    pending: list[Event] = field(default_factory=list)  # blueprint messages before any recording
    pending_bytes: int = 0
    store_infos: dict[StoreId, StoreInfoMessage] = field(default_factory=dict)  # to reopen a sealed run
    report: IngestReport = field(default_factory=IngestReport)


class RunFacts:
    """What the catalog will say about a run, learnt from its messages (live, recovered or sealed)."""

    def __init__(self, run_id: str, now: dt.datetime) -> None:
        self.run_id = run_id
        self.size = 0  # bytes of the recording, when it is not a hot file
        self.application_id = ""
        self.stores_written: set[StoreId] = set()
        self.activations: set[bytes] = set()
        self.chunk_ids: set[bytes] = set()
        self.summary: StoreSummary | None = None
        self.sdk_version: str | None = None
        self.robot_id: str | None = None
        self.properties: dict[str, dict[str, Any]] = {}
        self.start_time_ns: int | None = None
        self.first_log_time_ns: int | None = None
        self.created_at = now
        self.last_data_at = now
        self.live_sources = 0
        self.status = "live"
        self.ended_at: dt.datetime | None = None
        self.dirty = True

    def observe_store_info(self, msg: StoreInfoMessage) -> None:
        self.stores_written.add(msg.store_id)
        if msg.store_id.kind == StoreKind.RECORDING:
            self.application_id = msg.store_id.application_id
            self.sdk_version = str(msg.sdk_version) if msg.sdk_version else self.sdk_version
            if self.summary is None:
                self.summary = StoreSummary(msg.store_id)
        self.dirty = True

    def observe_chunk(self, msg: ArrowMessage, meta: ChunkMeta, now: dt.datetime) -> None:
        self.chunk_ids.add(meta.chunk_id)
        self.last_data_at = now
        self.dirty = True
        if msg.store_id.kind != StoreKind.RECORDING or self.summary is None:
            return
        self.summary.add_chunk(meta)
        for tl in meta.timelines:
            if tl.name == LOG_TIME and (self.first_log_time_ns is None or tl.range.min < self.first_log_time_ns):
                self.first_log_time_ns = tl.range.min

    def observe_property(self, name: str, values: dict[str, Any]) -> None:
        self.properties.setdefault(name or "recording", {}).update(values)
        if name == IDENTITY_PROPERTY and ROBOT_FIELD in values:
            self.robot_id = check_id("robot id", str(values[ROBOT_FIELD]))
        start = values.get(START_TIME_COMPONENT)
        if not name and isinstance(start, int):
            self.start_time_ns = start

    def replay(self, event: Event, at: dt.datetime, meta: ChunkMeta | None = None) -> None:
        """Learn a message already written (recovery after a restart, sealing)."""
        if isinstance(event, StoreInfoMessage):
            self.observe_store_info(event)
        elif isinstance(event, BlueprintActivationMessage):
            self.activations.add(bytes(event.raw))
        elif isinstance(event, ArrowMessage):
            meta = meta or chunk_meta(event)
            if event.store_id.kind == StoreKind.RECORDING and is_property_entity(meta.entity_path):
                prop = read_property_chunk(event, meta)
                self.observe_property(prop.name, prop.values)
            self.observe_chunk(event, meta, at)

    def recording_bytes(self) -> int:
        return self.size

    def record(self, default_robot: str) -> RunRecord:
        summary = self.summary
        started = self.start_time_ns or self.first_log_time_ns
        return RunRecord(
            id=self.run_id,
            robot_id=self.robot_id or default_robot,
            application_id=self.application_id,
            date=run_date(self.start_time_ns, self.first_log_time_ns, self.created_at),
            status=self.status,
            tier="hot",
            started_at=dt.datetime.fromtimestamp(started / 1e9, dt.UTC) if started else None,
            ended_at=self.ended_at,
            last_data_at=self.last_data_at,
            sdk_version=self.sdk_version,
            chunks=summary.chunks if summary else 0,
            rows=summary.rows if summary else 0,
            bytes=self.recording_bytes(),
            properties=self.properties,
            entities=[EntityRecord(e.path, e.chunks, e.static_chunks, e.rows, e.bytes, sorted(e.archetypes),
                                   sorted(e.components)) for e in summary.entities.values()] if summary else [],
            timelines=[TimelineRecord(t.name, t.type, t.min, t.max)
                       for t in summary.timelines.values()] if summary else [],
        )


class RunState(RunFacts):
    """A hot run: its file, the chunk ids it holds, and what the catalog will say about it."""

    def __init__(self, hot: HotRun, now: dt.datetime) -> None:
        super().__init__(hot.run_id, now)
        self.hot = hot
        self.sealing = threading.Lock()  # held by ingest per write, and by promotion as it hands the run over
        self.sealed = False  # handed to the warm tier: new data for this run starts a new hot run
        self.sealed_as: SealedInfo | None = None  # this hot run adds chunks to a run already sealed
        self.promote_failures = 0
        self.next_promote_at: dt.datetime | None = None  # backoff after a failed promotion

    def recording_bytes(self) -> int:
        return self.hot.size  # the hot file knows its size


class IngestService:
    def __init__(self, hot: HotStore, catalog: sessionmaker[Session] | None, *, default_robot: str,
                 max_streams: int, close_after: dt.timedelta, clock: Callable[[], dt.datetime] = utcnow,
                 replay: ReplayHub | None = None, sealed_lookup: SealedLookup | None = None,
                 secret_fields: SecretFields | None = None) -> None:
        self.hot = hot
        self.secret_fields = secret_fields or SecretFields()  # property fields stripped (FLEET_SECRET_FIELDS)
        self.sealed_lookup = sealed_lookup  # asked when a run id is not hot here: was it sealed?
        self.replay = replay  # what live streams bring, for ReadMessages readers
        self.catalog = catalog
        self.default_robot = default_robot
        self.max_streams = max_streams
        self.close_after = close_after
        self.clock = clock
        self.runs: dict[str, RunState] = {}
        self.live_streams = 0
        self.totals = {"chunks_new": 0, "chunks_duplicate": 0, "bytes_new": 0, "messages": 0}

    # --- sources ---------------------------------------------------------------------------

    def open_source(self, *, live: bool) -> Source:
        if live:
            if self.live_streams >= self.max_streams:
                raise TooManyStreamsError(
                    f"this node already holds {self.live_streams} streams, its limit (FLEET_MAX_STREAMS); "
                    "retry later or send to another node")
            self.live_streams += 1
        return Source(live=live)

    def close_source(self, source: Source) -> IngestReport:
        """End of a stream or upload: its runs are closed unless another stream still feeds them."""
        if source.live:
            self.live_streams -= 1
        for key in self.totals:
            self.totals[key] += getattr(source.report, key)
        if source.pending:
            log.warning("dropped %d blueprint messages that came with no recording", len(source.pending))
        runs = [self.runs[r] for r in source.report.runs if r in self.runs]
        self.hot.sync_if_always([r.hot for r in runs])
        now = self.clock()
        for run in runs:
            if source.live:
                run.live_sources -= 1
            if run.live_sources == 0 and run.status == "live":
                run.status, run.ended_at, run.dirty = "closed", now, True
        if not source.live:
            self.flush_catalog()  # an upload is answered with the catalog already up to date
        return source.report

    def accept(self, source: Source, event: Event) -> None:
        """File one message of `source`."""
        source.report.messages += 1
        if isinstance(event, StreamStart):
            source.version = event.version
        elif isinstance(event, StoreInfoMessage):
            self._store_info(source, event)
        elif isinstance(event, ArrowMessage):
            self._arrow(source, event)
        elif isinstance(event, BlueprintActivationMessage):
            self._activation(source, event)

    # --- messages --------------------------------------------------------------------------

    def _store_info(self, source: Source, msg: StoreInfoMessage) -> None:
        store = msg.store_id
        if store.kind == StoreKind.BLUEPRINT:
            if source.recording_run is None:
                self._hold(source, msg)
                return
            run = self._state(source, source.recording_run)
        else:
            run_id = check_id("recording id", store.recording_id)
            run = self._run_for(source, run_id, msg.sdk_version)
            source.recording_run = source.recording_run or run_id
        source.run_of_store[store] = run.run_id
        source.store_infos[store] = msg
        if store not in run.stores_written:
            run = self._append(source, run, MessageKind.SET_STORE_INFO, msg.raw)
            run.observe_store_info(msg)
            self._publish(source, MessageKind.SET_STORE_INFO, msg.raw, persistent=True)
        if source.pending and source.recording_run == run.run_id:
            pending, source.pending, source.pending_bytes = source.pending, [], 0
            for event in pending:
                self.accept(source, event)
                source.report.messages -= 1  # counted when it arrived

    def _run_for(self, source: Source, run_id: str, version: RerunVersion | None) -> RunState:
        run = self.runs.get(run_id)
        if run is None or run.sealed:
            run = self._new_run(run_id, version or source.version or DEFAULT_VERSION)
        if run_id not in source.report.runs:
            source.report.runs.append(run_id)
            if source.live:
                run.live_sources += 1
        if source.live and run.status != "live":
            run.status, run.ended_at, run.dirty = "live", None, True
        return run

    def _new_run(self, run_id: str, version: RerunVersion) -> RunState:
        sealed = self.sealed_lookup(run_id) if self.sealed_lookup is not None else None
        if sealed is not None and sealed.tier != "warm":
            fix = ("restore it first (fleet runs restore)" if sealed.tier == "cold"
                   else "send it under a new recording id")
            raise SealedRunError(f"run {run_id!r} is {sealed.tier}: it takes no new data; {fix}")
        self.hot.check_space(0)
        run = self.runs[run_id] = RunState(self.hot.create(run_id, version), self.clock())
        if sealed is not None:  # chunks sent after it was sealed: kept, and sealed in with the rest later
            run.sealed_as = sealed
            run.chunk_ids |= sealed.chunk_ids
        return run

    def _state(self, source: Source, run_id: str) -> RunState:
        run = self.runs.get(run_id)
        return self._reopen(source, run_id) if run is None or run.sealed else run

    def _reopen(self, source: Source, run_id: str) -> RunState:
        """The run was sealed into the warm tier while this source was still sending: what follows
        starts a new hot run (with the source's store infos), sealed in with the rest later."""
        run = self._new_run(run_id, source.version or DEFAULT_VERSION)
        run.live_sources = 1 if source.live else 0
        for store, info in source.store_infos.items():
            if source.run_of_store.get(store) == run_id:
                run.hot.append(MessageKind.SET_STORE_INFO, info.raw)
                run.observe_store_info(info)
        return run

    def _append(self, source: Source, run: RunState, kind: MessageKind, raw: Buffer) -> RunState:
        """Write one message to the run's hot file, unless promotion has just taken the run."""
        while True:
            with run.sealing:
                if not run.sealed:
                    run.hot.append(kind, raw)
                    return run
            run = self._reopen(source, run.run_id)

    def forget(self, run: RunState) -> None:
        """Promotion sealed this run: it leaves the hot tier (called with `run.sealing` held)."""
        if self.runs.get(run.run_id) is run:
            del self.runs[run.run_id]
        self.hot.forget(run.hot)

    def _arrow(self, source: Source, msg: ArrowMessage) -> None:
        run = self._run_of(source, msg.store_id, msg)
        if run is None:
            return
        if msg.chunk_id is not None and msg.chunk_id in run.chunk_ids:
            source.report.chunks_duplicate += 1
            return
        meta = chunk_meta(msg)
        if meta.chunk_id in run.chunk_ids:
            source.report.chunks_duplicate += 1
            return
        check_chunk(msg, meta)  # what Rerun refuses, and full validation of chunks whose values are read
        if msg.store_id.kind == StoreKind.RECORDING and is_property_entity(meta.entity_path):
            prop = read_property_chunk(msg, meta, self.secret_fields)
            run.observe_property(prop.name, prop.values)
            msg, meta = prop.message, prop.meta  # without its secret fields, if it had any
        self.hot.check_space(len(msg.raw))
        run = self._append(source, run, MessageKind.ARROW_MSG, msg.raw)
        run.observe_chunk(msg, meta, self.clock())
        self._publish(source, MessageKind.ARROW_MSG, msg.raw, persistent=msg.store_id.is_blueprint,
                      static=meta.is_static)
        if source.live and run.status != "live":  # closed as idle, and its stream speaks again
            run.status, run.ended_at = "live", None
        source.report.chunks_new += 1
        source.report.bytes_new += len(msg.raw)

    def _activation(self, source: Source, msg: BlueprintActivationMessage) -> None:
        run = self._run_of(source, msg.blueprint_id, msg)
        if run is not None and bytes(msg.raw) not in run.activations:
            run = self._append(source, run, MessageKind.BLUEPRINT_ACTIVATION, msg.raw)
            run.activations.add(bytes(msg.raw))
            self._publish(source, MessageKind.BLUEPRINT_ACTIVATION, msg.raw, persistent=True)

    def _publish(self, source: Source, kind: MessageKind, raw: Buffer, *, persistent: bool,
                 static: bool = False) -> None:
        if source.live and self.replay is not None:
            self.replay.publish(kind, raw, persistent=persistent, static=static)

    def _run_of(self, source: Source, store: StoreId, msg: Event) -> RunState | None:
        run_id = source.run_of_store.get(store)
        if run_id is not None:
            return self._state(source, run_id)
        if store.kind == StoreKind.BLUEPRINT:
            self._hold(source, msg)
            return None
        raise InvalidStreamError(
            f"a message for recording {store.recording_id!r} came before its SetStoreInfo "
            f"(at byte {getattr(msg, 'offset', 0)}): send the recording from its start")

    def _hold(self, source: Source, msg: Event) -> None:
        """Blueprints are sent before their recording: keep them until it is known (bounded)."""
        size = len(getattr(msg, "raw", b""))
        if source.pending_bytes + size > _PENDING_LIMIT:
            raise InvalidStreamError(f"more than {_PENDING_LIMIT} bytes of blueprint with no recording")
        source.pending.append(msg)
        source.pending_bytes += size

    # --- recovery, catalog, closing ----------------------------------------------------------

    def recover(self) -> list[str]:
        """Rebuild every hot run from disk after a restart (torn tails trimmed); returns their ids."""
        recovered = []
        for directory in self.hot.existing():
            hot, events = self.hot.recover(directory)
            mtime = dt.datetime.fromtimestamp(hot.path.stat().st_mtime, dt.UTC)
            run = self.runs[hot.run_id] = RunState(hot, mtime)
            for event in events:
                run.replay(event, mtime)
            # No stream survives a restart (the SDK never reconnects): what follows comes by upload.
            run.last_data_at, run.status, run.ended_at = mtime, "closed", mtime
            sealed = self.sealed_lookup(hot.run_id) if self.sealed_lookup is not None else None
            if sealed is not None and run.chunk_ids <= sealed.chunk_ids:
                # Promotion sealed it and stopped before removing the hot copy: finish that now.
                log.info("hot run %s is already sealed in the %s tier: removing the hot copy", hot.run_id, sealed.tier)
                del self.runs[hot.run_id]
                self.hot.discard(hot)
                continue
            if sealed is not None:
                run.sealed_as = sealed
                run.chunk_ids |= sealed.chunk_ids
            recovered.append(hot.run_id)
        self.flush_catalog()
        return recovered

    def close_idle(self) -> list[str]:
        """Close live runs that received nothing for `close_after`."""
        now = self.clock()
        closed = []
        for run in list(self.runs.values()):  # promotion may take runs away meanwhile
            if run.status == "live" and now - run.last_data_at >= self.close_after:
                run.status, run.ended_at, run.dirty = "closed", now, True
                closed.append(run.run_id)
        return closed

    def flush_catalog(self) -> None:
        """Write every run that changed to the catalog, in one transaction."""
        self.save_records(self.take_dirty_records())

    def take_dirty_records(self) -> list[RunRecord]:
        """Snapshots of the runs that changed since the last flush (cheap: taken on the ingest
        thread, then saved with `save_records`, which may run on another thread)."""
        records = []
        for run in list(self.runs.values()):
            if run.dirty:
                run.dirty = False
                records.append(run.record(self.default_robot))
        return records

    def save_records(self, records: list[RunRecord]) -> None:
        if not records or self.catalog is None:
            return
        now = self.clock()
        try:
            with session_scope(self.catalog) as session:
                for record in records:
                    queries.save_run(session, record, now)
        except Exception:
            for record in records:
                run = self.runs.get(record.id)
                if run is not None:
                    run.dirty = True  # retried at the next flush
            raise

    def close(self) -> None:
        self.flush_catalog()
        self.hot.close()
