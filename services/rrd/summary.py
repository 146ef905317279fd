"""What an RRD stream holds: stores, ids, SDK version, entities and timelines (for `fleet rrd inspect`)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from core.timefmt import timeline_value
from services.rrd import errors
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.layout import ChunkLayout
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    EndMessage,
    Event,
    StoreId,
    StoreInfoMessage,
    StreamFooter,
    StreamStart,
)


@dataclass
class EntitySummary:
    path: str
    chunks: int = 0
    static_chunks: int = 0
    rows: int = 0
    bytes: int = 0
    archetypes: set[str] = field(default_factory=set)
    components: set[str] = field(default_factory=set)


@dataclass
class TimelineSummary:
    name: str
    type: str
    min: int
    max: int


@dataclass
class StoreSummary:
    store_id: StoreId
    sdk_version: str | None = None
    source: str | None = None
    store_infos: int = 0
    chunks: int = 0
    rows: int = 0
    bytes: int = 0
    blueprint_activations: int = 0
    entities: dict[str, EntitySummary] = field(default_factory=dict)
    timelines: dict[str, TimelineSummary] = field(default_factory=dict)
    # The layout of each entity's last chunk: another chunk of it brings no archetype or component.
    _last_layouts: dict[str, ChunkLayout] = field(default_factory=dict, repr=False, compare=False)

    def add_chunk(self, meta: ChunkMeta) -> None:
        # Runs once per chunk: plain lookups, no objects built for what is already known.
        self.chunks += 1
        self.rows += meta.num_rows
        self.bytes += meta.byte_size
        entity = self.entities.get(meta.entity_path)
        if entity is None:
            entity = self.entities[meta.entity_path] = EntitySummary(meta.entity_path)
        entity.chunks += 1
        entity.static_chunks += meta.is_static
        entity.rows += meta.num_rows
        entity.bytes += meta.byte_size
        if self._last_layouts.get(meta.entity_path) is not meta.layout:
            entity.archetypes |= meta.archetypes
            entity.components |= meta.component_names
            self._last_layouts[meta.entity_path] = meta.layout
        for tl in meta.timelines:
            known = self.timelines.get(tl.name)
            if known is None:
                self.timelines[tl.name] = TimelineSummary(tl.name, tl.type, tl.range.min, tl.range.max)
            else:
                if tl.range.min < known.min:
                    known.min = tl.range.min
                if tl.range.max > known.max:
                    known.max = tl.range.max


@dataclass
class RrdSummary:
    source: str
    bytes_read: int = 0
    streams: int = 0
    rerun_versions: list[str] = field(default_factory=list)
    footers: int = 0
    stores: dict[StoreId, StoreSummary] = field(default_factory=dict)
    error: errors.RrdError | None = None
    index: str = "scan"  # "scan": every chunk read; "footer": from the file's RRD footer

    def store(self, store_id: StoreId) -> StoreSummary:
        return self.stores.setdefault(store_id, StoreSummary(store_id))

    def add_store_info(self, event: StoreInfoMessage) -> None:
        store = self.store(event.store_id)
        store.store_infos += 1
        store.sdk_version = str(event.sdk_version) if event.sdk_version else store.sdk_version
        store.source = event.source

    def add(self, event: Event) -> None:
        if isinstance(event, StreamStart):
            self.streams += 1
            self.rerun_versions.append(str(event.version))
        elif isinstance(event, StoreInfoMessage):
            self.add_store_info(event)
        elif isinstance(event, ArrowMessage):
            (self.stores.get(event.store_id) or self.store(event.store_id)).add_chunk(chunk_meta(event))
        elif isinstance(event, BlueprintActivationMessage):
            self.store(event.blueprint_id).blueprint_activations += 1
        elif isinstance(event, StreamFooter):
            self.footers += 1
        elif isinstance(event, EndMessage):
            pass

    def to_dict(self) -> dict[str, Any]:
        return {
            "source": self.source,
            "bytes": self.bytes_read,
            "streams": self.streams,
            "rerun_versions": self.rerun_versions,
            "footers": self.footers,
            "index": self.index,
            "error": None
            if self.error is None
            else {"type": type(self.error).__name__, "offset": self.error.offset, "message": str(self.error)},
            "stores": [_store_dict(s) for s in self.stores.values()],
        }


def _store_dict(store: StoreSummary) -> dict[str, Any]:
    return {
        "kind": store.store_id.kind.name.lower(),
        "application_id": store.store_id.application_id,
        "recording_id": store.store_id.recording_id,
        "sdk_version": store.sdk_version,
        "source": store.source,
        "chunks": store.chunks,
        "rows": store.rows,
        "bytes": store.bytes,
        "blueprint_activations": store.blueprint_activations,
        "entities": [
            {
                "path": e.path,
                "chunks": e.chunks,
                "static_chunks": e.static_chunks,
                "rows": e.rows,
                "bytes": e.bytes,
                "archetypes": sorted(e.archetypes),
                "components": sorted(e.components),
            }
            for e in sorted(store.entities.values(), key=lambda e: e.path)
        ],
        "timelines": [
            {
                "name": t.name,
                "type": t.type,
                "min": t.min,
                "max": t.max,
                "min_text": format_time(t.type, t.min),
                "max_text": format_time(t.type, t.max),
            }
            for t in sorted(store.timelines.values(), key=lambda t: t.name)
        ],
    }


def format_time(timeline_type: str, value: int) -> str:
    """A timeline value as people read it (the one formatter: core.timefmt)."""
    return timeline_value(timeline_type, value)


def summarize(events: Iterable[Event], source: str) -> RrdSummary:
    """Summarize a stream of events; a codec error stops the summary and is kept in `.error`
    (everything before it is counted)."""
    summary = RrdSummary(source)
    try:
        for event in events:
            summary.add(event)
    except errors.RrdError as exc:
        summary.error = exc
    return summary
