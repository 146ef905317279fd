"""Ingest: messages from live gRPC streams and from uploads, filed into runs, each chunk once.

A *source* is one gRPC `WriteMessages` stream or one upload. Its SetStoreInfo messages name the
recordings it carries; each recording is a run (run id = recording id). Blueprint stores are
kept with the recording they arrive beside. A chunk whose id the run already holds (sent live,
then uploaded from the FileSink copy) is counted as a duplicate and not written again.

A run becomes hot on this node with its first new data chunk, not with its SetStoreInfo, properties
or blueprint (held until then): a stream that is refused before any data, or a replay of chunks
already held (a robot's file copy of a sealed run, `rerun URL` pointed at the depot), leaves no run
behind and changes no run's facts.
Nothing here waits for the catalog or an object store: what ingest needs to know of runs sealed
earlier is asked by `prepare` on a worker thread, with a time limit, and a catalog that does not
answer only delays that knowledge until promotion, never the data.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import logging
import threading
import uuid
from collections import Counter
from collections.abc import Callable

from cachetools import FIFOCache
from sqlalchemy.orm import Session, sessionmaker

from catalog.queries import RunRecord
from core.clock import utcnow
from core.errors import ConflictError, InvalidArgumentError, PermissionDeniedError, ResourceExhaustedError
from core.ids import UnsafeIdError, check_id, check_name
from core.states import RunStatus, Tier
from services.cluster.ownership import Lease, Ownership
from services.cluster.relay import Channels
from services.facts.identity import IDENTITY_PROPERTY, ROBOT_FIELD, SecretFields, check_robot, read_property_chunk
from services.facts.run import LOG_TIME, RunFacts, check_chunk_names, store_key
from services.facts.sealed import SealedInfo, SealedLookup
from services.hot.read import HotRecording, read_events
from services.hot.store import HotStore
from services.ingest.catalog_sync import CatalogSync
from services.ingest.replay import ReplayHub
from services.ingest.routing import route
from services.ingest.run import IngestRun
from services.ingest.source import IngestReport, Source
from services.ingest.view import HandedOver, HotRunView, view_of
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.frames import DEFAULT_VERSION, MessageKind
from services.rrd.layout import ChunkLayout
from services.rrd.manifest import is_property_entity
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    Buffer,
    Event,
    StoreInfoMessage,
    StoreKind,
    StreamStart,
)
from services.rrd.validate import check_chunk
from services.rules.observe import ChunkObserver

__all__ = [
    "LOG_TIME",
    "ConflictError",
    "IngestReport",
    "IngestRun",
    "IngestService",
    "InvalidArgumentError",
    "ResourceExhaustedError",
    "RunFacts",
    "SealedInfo",
    "SealedLookup",
    "Source",
]

log = logging.getLogger(__name__)

_HELD_LIMIT = 64 * 1024 * 1024
# Layouts whose names were checked: a plain dict cleared when full, not a cachetools cache, as it is
# read for every chunk and a dict's lookup costs a sixth of an LRUCache's.
_NAMED_LAYOUTS = 4096
_RECENTLY_SEALED = 1024

# What a hand-over commits under the run's lock, given the run's lease: where the run went, if anywhere.
Commit = Callable[[Lease | None], SealedInfo | None]


class IngestService:
    def __init__(
        self,
        hot: HotStore,
        catalog: sessionmaker[Session] | None,
        *,
        default_robot: str,
        max_streams: int,
        close_after: dt.timedelta,
        clock: Callable[[], dt.datetime] = utcnow,
        replay: ReplayHub | None = None,
        sealed_lookup: SealedLookup | None = None,
        lookup_timeout_s: float = 2.0,
        secret_fields: SecretFields | None = None,
        ownership: Ownership | None = None,
        channels: Channels | None = None,
        observer: ChunkObserver | None = None,
    ) -> None:
        self.hot = hot
        # Told of each new recording chunk (not a property) that it wants: the rules, live. None on
        # the robot agent's spool.
        self.observer = observer
        # Many nodes on one catalog: who owns which run (None: this node files everything it gets).
        self.ownership = ownership
        self.channels = channels  # to the peer ports of runs' owners
        self.open_claims: Counter[str] = Counter()  # runs routed here by sources still open
        # This process's hot tier, as the agents' `held` checks name it: a new one after a restart.
        self.incarnation = f"{ownership.node_id if ownership else 'depot'}/{uuid.uuid4().hex[:12]}"
        self.secret_fields = secret_fields or SecretFields()  # property fields stripped (FLEET_SECRET_FIELDS)
        self.sealed_lookup = sealed_lookup  # asked (off the event loop) when a run id is not hot here
        self.lookup_timeout_s = lookup_timeout_s
        self.replay = replay  # what live streams bring, for ReadMessages readers
        self.catalog = catalog
        self.default_robot = default_robot
        self.max_streams = max_streams
        self.close_after = close_after
        self.clock = clock
        self.runs: dict[str, IngestRun] = {}
        # Runs this node sealed lately, for data that follows a promotion while the catalog does not
        # answer: the last sealed stay. Written by promotion's thread, read by ingest's: locked.
        self.recently_sealed: FIFOCache[str, SealedInfo] = FIFOCache(_RECENTLY_SEALED)
        self._recently_sealed_lock = threading.Lock()
        self.live_streams = 0
        self.totals = {"chunks_new": 0, "chunks_duplicate": 0, "bytes_new": 0, "bytes_duplicate": 0, "messages": 0}
        self._catalog_sync = CatalogSync(catalog, self.clock)
        self._named: dict[int, ChunkLayout] = {}  # layouts whose entity and timeline names were checked

    # --- the hot runs as other services see them (read-only: only ingest changes `runs`) ------

    def hot_run(self, run_id: str) -> HotRunView | None:
        """The run if it is hot here and not handed over (late additions to a sealed run included)."""
        run = self.runs.get(run_id)
        return view_of(run) if run is not None and not run.handed_over else None

    def hot_runs(self) -> list[HotRunView]:
        """This node's hot runs not handed over, oldest data first, as they are now (promotion may
        take runs away meanwhile)."""
        views = [view_of(run) for run in list(self.runs.values()) if not run.handed_over]
        return sorted(views, key=lambda run: run.last_data_at)

    def closed_runs(self) -> list[HotRunView]:
        """Hot runs that no stream feeds any more, oldest data first: those promotion may seal."""
        return [run for run in self.hot_runs() if run.status == RunStatus.CLOSED and not run.live_sources]

    def run_counts(self) -> tuple[int, int]:
        """How many runs this node holds hot, and how many of them are live (for /metrics)."""
        runs = list(self.runs.values())
        return len(runs), sum(run.status == RunStatus.LIVE for run in runs)

    def hot_recording(self, run_id: str) -> HotRecording | None:
        """A run in the hot tier as readers see it (`HotRuns`). Taken from here rather than the
        catalog, so a run is served from its first chunk (the catalog lags a little). None when the
        run is not hot here, or is sealed and only its late additions are hot."""
        run = self.runs.get(run_id)
        if run is None or run.adds_to is not None:
            return None
        hot = run.hot

        def follow() -> tuple[int, bool]:
            return hot.size, run.status == RunStatus.LIVE

        types = {t.name: t.type for t in run.summary.timelines.values()} if run.summary else {}
        return HotRecording(hot.path, hot.size, types, follow, hot.changes)

    # --- sources ---------------------------------------------------------------------------

    def open_source(self, *, live: bool, robot: str | None = None) -> Source:
        """A stream or upload about to bring messages; `robot`: the only robot whose runs it may
        write (its token's), None for any."""
        if live:
            if self.live_streams >= self.max_streams:
                raise ResourceExhaustedError(
                    f"this node already holds {self.live_streams} streams, its limit (FLEET_MAX_STREAMS); "
                    "retry later or send to another node"
                )
            self.live_streams += 1
        return Source(live=live, robot=robot)

    async def end_source(self, source: Source) -> IngestReport:
        """`close_source` for a caller on the event loop: the fsync durability=always asks for runs
        on a worker thread (a disk that takes a second to sync stalls no other stream). Its runs stay
        open meanwhile, so nothing seals them under the sync; cancelled, the source still closes."""
        try:
            await asyncio.to_thread(self.hot.sync_if_always, [r.hot for r in self._attached_runs(source)])
        finally:
            report = self.close_source(source, synced=True)
        return report

    def _attached_runs(self, source: Source) -> list[IngestRun]:
        return [self.runs[r] for r in source.attached if r in self.runs]

    def close_source(self, source: Source, *, synced: bool = False) -> IngestReport:
        """End of a stream or upload: its runs are closed unless another stream still feeds them.
        Blocks on fsync with durability=always unless `synced` (on the event loop: `end_source`)."""
        if source.live:
            self.live_streams -= 1
        for key in self.totals:
            self.totals[key] += getattr(source.report, key)
        if source.held:
            log.info("dropped %d held messages of runs that received no new chunk", len(source.held))
        if not source.live:
            source.report.warnings.extend(source.overlap_warnings())
            for warning in source.report.warnings:
                log.warning("upload: %s", warning)
        for run_id in source.routed:
            self.open_claims[run_id] -= 1
            if self.open_claims[run_id] <= 0:
                del self.open_claims[run_id]
        runs = self._attached_runs(source)
        if not synced:
            self.hot.sync_if_always([r.hot for r in runs])
        now = self.clock()
        for run in runs:
            run.sources -= 1
            if source.live:
                run.live_sources -= 1
            if run.live_sources == 0 and run.status == RunStatus.LIVE:
                self._close_run(run, now)
        return source.report

    async def finish_upload(self, source: Source, timeout_s: float = 10.0) -> IngestReport:
        """Close an upload and bring the catalog up to date before it is answered; a catalog that is
        down or slow leaves the answer saying so (the data is kept; the catalog catches up later)."""
        report = await self.end_source(source)
        records = self.take_dirty_records()
        try:
            await asyncio.wait_for(asyncio.to_thread(self.save_records, records), timeout_s)
        except Exception as exc:  # any catalog failure: retried by the housekeeping
            log.warning("catalog not updated after an upload (%s); it catches up when it answers", exc)
            self._catalog_sync.mark_dirty(records, self.runs)
            report.catalog = "pending"
        return report

    async def remove_dropped(self, timeout_s: float = 10.0) -> None:
        """Runs dropped by a refusal leave the catalog now (off the event loop), so that once the
        refusal is answered no one finds them; a catalog that is slow or down leaves it to the next
        flush."""
        if not self._catalog_sync.dropped:
            return
        try:
            await asyncio.wait_for(asyncio.to_thread(self._catalog_sync.save, [], self.runs), timeout_s)
        except Exception as exc:  # retried by the housekeeping
            log.warning("dropped runs not yet removed from the catalog (%s); the next flush does it", exc)

    async def prepare(self, source: Source, event: Event) -> None:
        """Before `accept`: for a recording not hot here, ask (on a worker thread, within
        `lookup_timeout_s`) whether it was sealed before, so late data is filed beside it and chunks
        it already holds are skipped. No answer in time: filed as new, sorted out at promotion."""
        if not isinstance(event, StoreInfoMessage) or event.store_id.kind != StoreKind.RECORDING:
            return
        run_id = event.store_id.recording_id
        try:
            check_id("recording id", run_id)
        except UnsafeIdError:
            return  # `accept` refuses the id with the reason
        await route(self, source, run_id)
        if self.sealed_lookup is None or source.relay_to is not None or run_id in source.sealed or run_id in self.runs:
            return
        try:
            source.sealed[run_id] = await asyncio.wait_for(
                asyncio.to_thread(self.sealed_lookup, run_id), self.lookup_timeout_s
            )
        except Exception as exc:  # catalog or store down or slow: the data still goes in
            self._lookup_failed(source, run_id, exc)

    def _lookup_failed(self, source: Source, run_id: str, exc: BaseException) -> None:
        log.warning(
            "could not ask the catalog whether run %s was sealed (%s): filing its data as new; "
            "promotion merges it with a sealed copy if there is one",
            run_id,
            type(exc).__name__,
        )
        source.sealed[run_id] = None

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
        key = store_key(store)
        if store.kind == StoreKind.BLUEPRINT:
            if source.recording_run is None:
                self._hold(source, None, msg)
                return
            run_id = source.recording_run
        else:
            run_id = check_id("recording id", store.recording_id)
            check_name("application id", store.application_id)
            source.recording_run = source.recording_run or run_id
            if run_id not in source.report.runs:
                source.report.runs.append(run_id)
        source.run_of_store[key] = run_id
        source.store_infos[key] = msg
        run = self._hot_run(source, run_id)
        if run is not None and key not in run.stores_written:
            run = self._append(source, run, MessageKind.SET_STORE_INFO, msg.raw, store.kind)
            run.observe_store_info(msg)
            self._publish(source, run.run_id, MessageKind.SET_STORE_INFO, msg.raw, persistent=True)
        if store.kind == StoreKind.RECORDING and run_id == source.recording_run:
            self._release(source, None)  # blueprints that came before their recording

    def _arrow(self, source: Source, msg: ArrowMessage) -> None:
        run_id = self._run_id_of(source, msg.store_id.kind, msg.store_id.recording_id, msg)
        if run_id is None:
            return
        run = self._hot_run(source, run_id)
        held = self._held_before(source, run, run_id)
        if msg.chunk_id is not None and self._holds(source, run, run_id, msg.chunk_id):
            self._duplicate(source, run_id, msg, held)
            return
        meta = chunk_meta(msg)
        if meta.chunk_id != msg.chunk_id and self._holds(source, run, run_id, meta.chunk_id):
            self._duplicate(source, run_id, msg, held)
            return
        if msg.store_id.kind == StoreKind.RECORDING:
            source.count_chunk(run_id, held, duplicate=False)
        if self._named.get(id(meta.layout)) is not meta.layout:  # the names are the layout's
            check_chunk_names(meta)
            if len(meta.timelines) == len(meta.layout.indexes):  # all of them were checked
                if len(self._named) >= _NAMED_LAYOUTS:
                    self._named.clear()
                self._named[id(meta.layout)] = meta.layout
        check_chunk(msg, meta)  # what Rerun refuses, and full validation of chunks whose values are read
        prop = None
        if is_property_entity(meta.entity_path):  # of any store kind: a blueprint's are stripped too
            prop = read_property_chunk(msg, meta, self.secret_fields)
            msg, meta = prop.message, prop.meta  # without its secret fields, if it had any
            if msg.store_id.kind != StoreKind.RECORDING:
                prop = None  # a blueprint's properties say nothing of the run
            elif prop.name == IDENTITY_PROPERTY and ROBOT_FIELD in prop.values:
                self._check_named_robot(source, run, str(prop.values[ROBOT_FIELD]))
        if run is None and (prop is not None or msg.store_id.kind == StoreKind.BLUEPRINT):
            self._hold(source, run_id, msg)  # a run starts with its data, not with properties or a layout
            return
        self.hot.check_space(len(msg.raw))
        run = run or self._materialize(source, run_id)
        run = self._append(source, run, MessageKind.ARROW_MSG, msg.raw, msg.store_id.kind, meta)
        if prop is not None:
            run.observe_property(prop.name, prop.values)
        run.observe_chunk(msg, meta, self.clock())
        if self.observer is not None and prop is None and msg.store_id.kind == StoreKind.RECORDING:
            self._observe(self.observer, run, msg, meta)
        if source.live and run.status != RunStatus.LIVE:  # closed as idle, and its stream speaks again
            run.status, run.ended_at = RunStatus.LIVE, None
            self._republish_store_infos(source, run.run_id)
        self._publish(
            source,
            run.run_id,
            MessageKind.ARROW_MSG,
            msg.raw,
            persistent=msg.store_id.is_blueprint,
            static=meta.is_static,
        )
        source.report.chunks_new += 1
        source.report.bytes_new += len(msg.raw)
        chunks, size = source.new_of_run.get(run.run_id, (0, 0))
        source.new_of_run[run.run_id] = (chunks + 1, size + len(msg.raw))

    def _observe(self, observer: ChunkObserver, run: IngestRun, msg: ArrowMessage, meta: ChunkMeta) -> None:
        if observer.wants(meta.entity_path):  # one dict lookup for the entities no rule names
            observer.chunk(run.run_id, run.robot_id or self.default_robot, msg, meta)

    def _check_named_robot(self, source: Source, run: IngestRun | None, robot: str) -> None:
        """A `robot_id` property that is no safe id, or disagrees with the source's token, is refused
        before anything of it is written, and the run this source started for it (filed under the
        token's robot, as its data came first) is dropped: nothing of a refused run is kept, and its
        id stays free for its own robot."""
        run_id = source.recording_run if run is None else run.run_id
        try:
            check_robot(source.robot, run_id or "", check_id("robot id", robot))
        except (PermissionDeniedError, UnsafeIdError):
            if run is not None and run.run_id in source.created and run.sources == 1:
                self._drop(source, run)
            elif run is None and run_id is not None:  # the property came first: nothing of it was written
                self._refused_before_kept(source, run_id)
            raise

    @staticmethod
    def _refused_before_kept(source: Source, run_id: str) -> None:
        if run_id in source.new_of_run:  # chunks of it went to a hot run since handed over: they stay
            return
        source.report.drop_run(run_id)

    def _drop(self, source: Source, run: IngestRun) -> None:
        with run.leaving:
            if run.handed_over:  # promotion took it meanwhile: it stays, and says so
                log.warning("run %s was sealed before its robot was refused; delete it if unwanted", run.run_id)
                return
            run.handed_over = True  # nothing more is written to it
        del self.runs[run.run_id]
        source.attached.discard(run.run_id)
        source.report.drop_run(run.run_id)
        chunks, size = source.new_of_run.pop(run.run_id, (0, 0))  # nothing of it is kept: not counted as kept
        source.report.chunks_new -= chunks
        source.report.bytes_new -= size
        self.hot.discard(run.hot)
        self._catalog_sync.drop(run.run_id)
        if self.replay is not None:
            self.replay.end_run(run.run_id)
        log.info("dropped run %s: its robot_id property was refused", run.run_id)

    def _activation(self, source: Source, msg: BlueprintActivationMessage) -> None:
        run_id = self._run_id_of(source, msg.blueprint_id.kind, msg.blueprint_id.recording_id, msg)
        if run_id is None:
            return
        run = self._hot_run(source, run_id)
        if run is None:
            self._hold(source, run_id, msg)
        elif bytes(msg.raw) not in run.activations:
            run = self._append(source, run, MessageKind.BLUEPRINT_ACTIVATION, msg.raw, StoreKind.BLUEPRINT)
            run.activations.add(bytes(msg.raw))
            self._publish(source, run.run_id, MessageKind.BLUEPRINT_ACTIVATION, msg.raw, persistent=True)

    def _run_id_of(self, source: Source, kind: StoreKind, recording_id: str, msg: Event) -> str | None:
        run_id = source.run_of_store.get((kind, recording_id))
        if run_id is not None:
            return run_id
        if kind == StoreKind.BLUEPRINT:
            self._hold(source, None, msg)
            return None
        raise InvalidArgumentError(
            f"a message for recording {recording_id!r} came before its SetStoreInfo "
            f"(at byte {getattr(msg, 'offset', 0)}): send the recording from its start"
        )

    def _duplicate(self, source: Source, run_id: str, msg: ArrowMessage, held: Callable[[], bool]) -> None:
        source.report.chunks_duplicate += 1
        source.report.bytes_duplicate += len(msg.raw)
        if msg.store_id.kind == StoreKind.RECORDING:
            source.count_chunk(run_id, held, duplicate=True)

    def _held_before(self, source: Source, run: IngestRun | None, run_id: str) -> Callable[[], bool]:
        """Whether the run had chunks before `source` fed it (asked once, at its first chunk)."""

        def held() -> bool:
            if run_id in source.created:
                return False
            sealed = run.adds_to if run is not None else self._sealed_info(source, run_id)
            return bool(run is not None and run.chunk_ids) or bool(sealed is not None and sealed.chunk_ids)

        return held

    def _holds(self, source: Source, run: IngestRun | None, run_id: str, chunk_id: bytes) -> bool:
        if run is not None:
            return run.holds(chunk_id)
        sealed = self._sealed_info(source, run_id)
        if sealed is None:
            return False
        # A robot's token writes its own runs only, even when all it sends is held already: a
        # 403 rather than "0 new" for another robot's sealed run (a hot one is checked on attach).
        check_robot(source.robot, run_id, sealed.robot_id)
        return chunk_id in sealed.chunk_ids

    def _sealed_info(self, source: Source, run_id: str) -> SealedInfo | None:
        """What the catalog said when `prepare` asked (its tier is the one that counts: a run sealed
        here may have been archived since), else what this node remembers sealing."""
        asked = source.sealed.get(run_id)
        if asked is not None:
            return asked
        with self._recently_sealed_lock:
            return self.recently_sealed.get(run_id)

    def _hot_run(self, source: Source, run_id: str) -> IngestRun | None:
        """The run if it is hot here (and not being handed over), counted as fed by `source`."""
        run = self.runs.get(run_id)
        if run is None or run.handed_over:
            return None
        self._attach(source, run)
        return run

    def _attach(self, source: Source, run: IngestRun) -> None:
        if source.robot is not None and run.run_id not in source.attached:
            check_robot(source.robot, run.run_id, run.robot_id or self.default_robot)
        if run.run_id not in source.attached:
            source.attached.add(run.run_id)
            run.sources += 1
            if source.live:
                run.live_sources += 1

    def _materialize(self, source: Source, run_id: str) -> IngestRun:
        """The first new chunk of a run not hot here: a hot run with the source's store infos and
        whatever it held for it. A run sealed before takes the late data beside its sealed copy."""
        sealed = self._sealed_info(source, run_id)
        if sealed is not None and sealed.tier != Tier.WARM:
            fix = (
                "restore it first (fleet runs restore)"
                if sealed.tier == Tier.COLD
                else "send it under a new recording id"
            )
            raise ConflictError(f"run {run_id!r} is {sealed.tier}: it takes no new data; {fix}")
        if sealed is not None:
            check_robot(source.robot, run_id, sealed.robot_id)
        info = source.store_infos.get((StoreKind.RECORDING, run_id))
        version = (info.sdk_version if info is not None else None) or source.version or DEFAULT_VERSION
        hot = self.hot.create(run_id, version, source.robot)
        run = self.runs[run_id] = IngestRun(hot, self.clock(), self.secret_fields)
        run.robot_id = source.robot or run.robot_id  # the token's robot, until a property names the same one
        run.adds_to = sealed  # chunks sent after it was sealed: sealed in with the rest later
        run.lease = source.leases.get(run_id)
        source.created.add(run_id)
        self._attach(source, run)
        if self.observer is not None:
            self.observer.started(run_id, run.robot_id or self.default_robot)
        for key, store_info in source.store_infos.items():
            if source.run_of_store.get(key) == run_id and key not in run.stores_written:
                run.hot.append(MessageKind.SET_STORE_INFO, store_info.raw, key[0])
                run.observe_store_info(store_info)
                self._publish(source, run_id, MessageKind.SET_STORE_INFO, store_info.raw, persistent=True)
        self._release(source, run_id)
        return run

    def _append(
        self,
        source: Source,
        run: IngestRun,
        kind: MessageKind,
        raw: Buffer,
        store_kind: StoreKind,
        meta: ChunkMeta | None = None,
    ) -> IngestRun:
        """Write one message to the run's hot file (and its chunk index: `store_kind`, and a chunk's
        `meta`), unless it has just been handed over (then to a new hot run of the same id)."""
        while True:
            with run.leaving:
                if not run.handed_over:
                    run.hot.append(kind, raw, store_kind, meta)
                    return run
            run = self._materialize(source, run.run_id)

    def _hold(self, source: Source, run_id: str | None, msg: Event) -> None:
        size = len(getattr(msg, "raw", b""))
        if source.held_bytes + size > _HELD_LIMIT:
            raise InvalidArgumentError(f"more than {_HELD_LIMIT} bytes of blueprint came with no recording data")
        source.held.append((run_id, msg))
        source.held_bytes += size

    def _release(self, source: Source, run_id: str | None) -> None:
        """File the messages held for `run_id` (None: those that waited for a recording)."""
        if not any(held_for == run_id for held_for, _ in source.held):
            return
        ready = [event for held_for, event in source.held if held_for == run_id]
        source.held = [(held_for, event) for held_for, event in source.held if held_for != run_id]
        source.held_bytes = sum(len(getattr(event, "raw", b"")) for _, event in source.held)
        for event in ready:
            self.accept(source, event)
            source.report.messages -= 1  # counted when it arrived

    def _publish(
        self, source: Source, run_id: str, kind: MessageKind, raw: Buffer, *, persistent: bool, static: bool = False
    ) -> None:
        if source.live and self.replay is not None:
            self.replay.publish(run_id, kind, raw, persistent=persistent, static=static)

    def _republish_store_infos(self, source: Source, run_id: str) -> None:
        for key, info in source.store_infos.items():
            if source.run_of_store.get(key) == run_id:
                self._publish(source, run_id, MessageKind.SET_STORE_INFO, info.raw, persistent=True)

    def _close_run(self, run: IngestRun, now: dt.datetime) -> None:
        run.status, run.ended_at, run.dirty = RunStatus.CLOSED, now, True
        run.hot.changes.notify()  # its followers finish their streams
        if self.replay is not None:
            self.replay.end_run(run.run_id)  # readers that connect later get live runs only

    # --- a hot run leaving this node's hot tier (the one place it happens), and its lease --------

    def hand_over(self, run: HotRunView, commit: Commit | None = None, *, doing: str, then: str) -> HandedOver:
        """`run` leaves this node's hot tier: sealed by promotion, handed to the node that owns it,
        or removed by the robot agent's retention. Under the run's lock (ingest waits there only if
        it has data for this very run): refused with a ConflictError saying what was under way
        (`doing`) and what happens next (`then`) if the run received data since `run` was taken
        (its size changed), is live, or a stream feeds it; else `commit` runs with the run's lease
        as it stands (promotion's catalog transaction; what it returns is where the run went,
        remembered for data that follows), and the run is marked handed over, forgotten and its
        folder set aside."""
        live = run._run
        with live.leaving:
            if live.handed_over or self.runs.get(run.run_id) is not live:
                raise ConflictError(f"run {run.run_id} left the hot tier while {doing}: nothing more to do")
            if live.hot.size != run.size or live.status == RunStatus.LIVE or live.live_sources:
                raise ConflictError(f"run {run.run_id} received data while {doing}: {then}")
            sealed_to = commit(live.lease) if commit is not None else None
            live.sealed_to, live.handed_over = sealed_to, True
            self._forget(live)
            return HandedOver(self.hot.set_aside(live.hot), live.lease)

    def has_left(self, run: HotRunView) -> bool:
        """Whether this hot run (not a later one of the same id) has left the hot tier."""
        return run._run.handed_over

    def set_adds_to(self, run: HotRunView, sealed: SealedInfo | None) -> None:
        """What the catalog says now of the run sealed before that `run` adds to (promotion asks:
        ingest may have filed the data while the catalog did not answer, or another node sealed it)."""
        run._run.adds_to = sealed

    def take_lease(self, run_id: str, lease: Lease) -> None:
        """This node owns the hot run (the ownership pass adopted or claimed it): its catalog row is
        written, and it is promoted here."""
        run = self.runs.get(run_id)
        if run is not None and not run.handed_over:
            run.lease, run.dirty = lease, True

    def lose_lease(self, run_id: str) -> None:
        """Another node owns the run now: its hot copy here is handed to that node."""
        run = self.runs.get(run_id)
        if run is not None and not run.handed_over:
            run.lease = None

    def _forget(self, run: IngestRun) -> None:
        """The run left the hot tier (called by `hand_over`, with `run.leaving` held)."""
        if self.runs.get(run.run_id) is run:
            del self.runs[run.run_id]
        if run.sealed_to is not None:
            with self._recently_sealed_lock:
                self.recently_sealed[run.run_id] = run.sealed_to  # sealed again: the newest again
        if self.replay is not None:
            self.replay.end_run(run.run_id)
        self.hot.forget(run.hot)

    # --- recovery, catalog, closing ----------------------------------------------------------

    def recover(self) -> list[str]:
        """Rebuild every hot run from disk after a restart (torn tails trimmed); returns their ids.
        Whether one was sealed before is settled at its promotion, when the catalog is asked."""
        recovered = []
        self.hot.sweep()
        for directory in self.hot.existing():
            hot = self.hot.recover(directory)
            mtime = dt.datetime.fromtimestamp(hot.path.stat().st_mtime, dt.UTC)
            run = self.runs[hot.run_id] = IngestRun(hot, mtime, self.secret_fields)
            run.robot_id = hot.robot  # the robot of the token that started it, if its messages name none
            for event in read_events(hot.path, hot.size):  # read again as it streams: none kept
                run.replay(event, mtime)
            # No stream survives a restart (the SDK never reconnects): what follows comes by upload.
            run.last_data_at, run.status, run.ended_at = mtime, RunStatus.CLOSED, mtime
            recovered.append(hot.run_id)
        try:
            self.flush_catalog()
        except Exception as exc:  # the housekeeping retries; the runs are safe on disk
            log.warning("catalog not updated with the recovered runs yet (%s)", exc)
        return recovered

    def close_idle(self) -> list[str]:
        """Close live runs that received nothing for `close_after`."""
        now = self.clock()
        closed = []
        for run in list(self.runs.values()):  # promotion may take runs away meanwhile
            if run.status == RunStatus.LIVE and now - run.last_data_at >= self.close_after:
                self._close_run(run, now)
                closed.append(run.run_id)
        return closed

    def flush_catalog(self) -> None:
        """Write every run that changed to the catalog."""
        self.save_records(self.take_dirty_records())

    def take_dirty_records(self) -> list[RunRecord]:
        """Snapshots of the runs that changed since the last flush (`CatalogSync.take`)."""
        return self._catalog_sync.take(self.runs, self.default_robot, owned_only=self.ownership is not None)

    def save_records(self, records: list[RunRecord]) -> None:
        """Write them to the catalog (`CatalogSync.save`); may run on another thread."""
        self._catalog_sync.save(records, self.runs)

    def close(self) -> None:
        try:
            self.flush_catalog()
        except Exception as exc:  # the hot runs are on disk: the next start files them
            log.warning("catalog not updated at shutdown (%s)", exc)
        self.hot.close()
