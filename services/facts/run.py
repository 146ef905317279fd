"""What the catalog says about a run, learnt from its messages: `RunFacts`, for any recording (live
in ingest, recovered from disk, or being sealed). Below both ingest and the sealed format, which
each learn a run's facts this way.

Everything that reaches the catalog is checked or cleaned here first: names must fit its columns and
indexes (no NUL, bounded bytes), and property values must be plain JSON (no NaN, no NUL), so one run
can never make the catalog refuse the writes or queries of every other run.
"""

from __future__ import annotations

import datetime as dt
import math
from typing import Any

from catalog.queries import EntityRecord, RunRecord, TimelineRecord
from core.ids import PATH_BYTES, check_id, check_name
from core.states import RunStatus, Tier
from services.facts.identity import (
    DEFAULT_SECRETS,
    IDENTITY_PROPERTY,
    ROBOT_FIELD,
    START_TIME_COMPONENT,
    SecretFields,
    read_property_chunk,
    run_date,
)
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.manifest import is_property_entity
from services.rrd.messages import ArrowMessage, BlueprintActivationMessage, Event, StoreId, StoreInfoMessage, StoreKind
from services.rrd.summary import StoreSummary

LOG_TIME = "log_time"


def check_chunk_names(meta: ChunkMeta) -> None:
    """The entity path and timeline names of a chunk, before it is written anywhere."""
    check_name("entity path", meta.entity_path, PATH_BYTES)
    for timeline in meta.timelines:
        check_name("timeline name", timeline.name)


def plain_json(value: Any) -> Any:
    """A property value every catalog and JSON reader accepts: NaN and infinities as the strings
    "NaN", "Infinity", "-Infinity", NUL characters as U+FFFD, anything else unknown as text."""
    if isinstance(value, str):
        return value.replace("\x00", "\ufffd")
    if isinstance(value, bool) or value is None or isinstance(value, int):
        return value
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        if math.isinf(value):
            return "Infinity" if value > 0 else "-Infinity"
        return value
    if isinstance(value, dict):
        return {plain_json(str(k)): plain_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain_json(v) for v in value]
    return plain_json(str(value))


class RunFacts:
    """What the catalog will say about a run, learnt from its messages (live, recovered or sealed)."""

    def __init__(self, run_id: str, now: dt.datetime, secret_fields: SecretFields = DEFAULT_SECRETS) -> None:
        self.run_id = run_id
        self.secret_fields = secret_fields  # what reading its stored property chunks leaves out
        self.size = 0  # bytes of the recording, when it is not a hot file
        self.application_id = ""
        self.stores_written: set[tuple[StoreKind, str]] = set()
        self.activations: set[bytes] = set()
        self.chunk_ids: set[bytes] = set()  # chunks in this recording (for a hot run: in its hot file)
        self.summary: StoreSummary | None = None
        self.sdk_version: str | None = None
        self.robot_id: str | None = None
        self.properties: dict[str, dict[str, Any]] = {}
        self.start_time_ns: int | None = None
        self.first_log_time_ns: int | None = None
        self.created_at = now
        self.last_data_at = now
        self.live_sources = 0
        self.sources = 0  # streams and uploads feeding it now (live or not)
        self.status = RunStatus.LIVE
        self.ended_at: dt.datetime | None = None
        self.dirty = True

    def observe_store_info(self, msg: StoreInfoMessage) -> None:
        self.stores_written.add(store_key(msg.store_id))
        if msg.store_id.kind == StoreKind.RECORDING:
            if msg.store_id.application_id:
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
        self.properties.setdefault(plain_json(name or "recording"), {}).update(plain_json(values))
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
                prop = read_property_chunk(event, meta, self.secret_fields)
                self.observe_property(prop.name, prop.values)
            self.observe_chunk(event, meta, at)

    def recording_bytes(self) -> int:
        return self.size

    def record(self, default_robot: str) -> RunRecord:
        """The run's row as the catalog would file it. Also called off the event loop (a run's page
        before the catalog has its row) while ingest adds to the run: each dict and set is copied
        by one C-level call (list(), dict(), sorted()), which the GIL keeps whole, before it is walked."""
        summary = self.summary
        started = self.start_time_ns or self.first_log_time_ns
        return RunRecord(
            id=self.run_id,
            robot_id=self.robot_id or default_robot,
            application_id=self.application_id,
            date=run_date(self.start_time_ns, self.first_log_time_ns, self.created_at),
            status=self.status,
            tier=Tier.HOT,
            started_at=_from_ns(started) if started else None,
            ended_at=self.ended_at,
            last_data_at=self.last_data_at,
            sdk_version=self.sdk_version,
            chunks=summary.chunks if summary else 0,
            rows=summary.rows if summary else 0,
            bytes=self.recording_bytes(),
            properties={name: dict(values) for name, values in list(self.properties.items())},
            entities=[
                EntityRecord(
                    e.path, e.chunks, e.static_chunks, e.rows, e.bytes, sorted(e.archetypes), sorted(e.components)
                )
                for e in list(summary.entities.values())
            ]
            if summary
            else [],
            timelines=[TimelineRecord(t.name, t.type, t.min, t.max) for t in list(summary.timelines.values())]
            if summary
            else [],
        )


def _from_ns(ns: int) -> dt.datetime | None:
    try:
        return dt.datetime.fromtimestamp(ns / 1e9, dt.UTC)
    except (OverflowError, OSError, ValueError):
        return None  # a start time no calendar holds: the run is dated by its data instead


def store_key(store: StoreId) -> tuple[StoreKind, str]:
    """A store as ingest tells stores apart: kind and recording id. Rerun 0.23 and 0.24 name the
    application only in SetStoreInfo, not in the store id of each chunk."""
    return store.kind, store.recording_id
