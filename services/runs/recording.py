"""`GET /v1/runs/{run}/recording.rrd` as a service: the run found hot on this node (its file read by
range as its chunk index plans, or followed while live) or sealed (ranged reads planned from its
chunk index alike), filtered by entity and time window, with an ETag naming the run's size and what
was asked."""

from __future__ import annotations

import hashlib
import json
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field

from sqlalchemy.orm import Session, sessionmaker

from core.clock import utcnow
from core.errors import BadParameterError
from services.hot.read import HotRecording, HotRuns
from services.runs import download, indexed, sealed
from services.sealed.read import SealedRecording, locate_sealed
from services.storage.objectstore import ObjectStore


@dataclass(frozen=True)
class RecordingQuery:
    """What a download asks for (the endpoint's query parameters)."""

    include: list[str] = field(default_factory=list)
    exclude: list[str] = field(default_factory=list)
    blueprint: bool = True
    timeline: str | None = None
    start: str | None = None
    end: str | None = None
    latest_at: bool = True
    follow: bool = False
    exact: bool = False


@dataclass(frozen=True)
class RecordingDownload:
    body: Iterator[bytes | memoryview] | AsyncIterator[bytes | memoryview]
    etag: str
    filename: str
    warnings: list[str] = field(default_factory=list)  # filters that match no entity of the run
    size: int | None = None  # the body's bytes, when known before it is sent (a sealed run whole)


def recording_download(
    hot_runs: HotRuns | None,
    catalog: sessionmaker[Session],
    warm: ObjectStore,
    run_id: str,
    query: RecordingQuery,
) -> RecordingDownload:
    """The run as an .rrd stream: hot runs from this node's disk (`hot_runs`: None on a node without
    ingest), any other from the warm store."""
    entities = download.EntityFilter(query.include, query.exclude)
    hot = hot_runs.hot_recording(run_id) if hot_runs is not None else None
    found: SealedRecording | None = None
    if hot is not None:
        types, size = hot.timeline_types, hot.size
    else:  # 404 naming the run, 409 for a cold run not restored, 410 for a deleted one
        # (its chunk index is read only when a time window needs the run's timelines, and
        # while the recording is looked at when anything is filtered out)
        windowed = query.timeline is not None or query.start is not None or query.end is not None
        filtered = windowed or not sealed.whole_object(entities, query.blueprint, None)
        found = locate_sealed(catalog, warm, run_id, utcnow(), index=filtered)
        types, size = found.timeline_types() if windowed else {}, found.size
    window = download.window_from_query(types, query.timeline, query.start, query.end, query.latest_at, query.exact)
    if query.follow and window is not None:
        raise BadParameterError("follow", "follow=true streams what comes next: it takes no time window")
    filters = json.dumps([sorted(entities.include), sorted(entities.exclude), query.blueprint, repr(window)])
    etag = f'"{run_id}-{size}-{hashlib.sha256(filters.encode()).hexdigest()[:16]}"'
    body: Iterator[bytes | memoryview] | AsyncIterator[bytes | memoryview]
    known_size = None
    if hot is not None and query.follow:  # waits for the run on the event loop, not in a thread of its own
        body = download.follow_run(hot, entities, blueprint=query.blueprint)
    elif hot is not None:
        body = indexed.stream_hot(hot, entities, blueprint=query.blueprint, window=window)
    else:
        assert found is not None  # not hot: located sealed above
        whole = sealed.whole_object(entities, query.blueprint, window)
        on_loop = sealed.whole_on_loop(found) if whole else None
        body = on_loop or sealed.stream_sealed(found, entities, blueprint=query.blueprint, window=window)
        known_size = found.size if whole else None
    warnings = entities.unmatched(_entity_paths(hot, found)) if entities.include or entities.exclude else []
    return RecordingDownload(body, etag, f"{run_id}.rrd", warnings, known_size)


def _entity_paths(hot: HotRecording | None, found: SealedRecording | None) -> set[str]:
    """The run's entities as its chunk index has them (hot: read again from the index file beside
    the run; only when a filter is asked for, to say which patterns match nothing)."""
    if hot is not None:
        return {e.meta.entity_path for e in hot.index_entries() if e.meta is not None}
    assert found is not None
    return found.index.entity_paths()
