"""What an RRD holds, per entity, read with the depot's own decoder: the chunks, how many messages
each entity has (distinct `message_log_time` values, which is what an MCAP topic's message count
becomes), and one component's rows in log-time order.

Why distinct log times rather than rows: Rerun's MCAP converter splits a topic over several chunks
(a PointCloud2 topic gets one chunk per message for its points and one for its other fields), and a
depot may re-chunk what it stores; the messages per topic survive both.

    chunks = read_rrd(path)
    message_counts(chunks)                                  {"/tf": 3, "/__mcap_properties": 0, ...}
    values(chunks, "/tf", "Transform3D:translation")        [[[1.0, 2.0, 3.0]], [[2.0, 2.0, 3.0]], ...]
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import pyarrow as pa

from services.rrd import ArrowMessage, iter_events, read_chunk

LOG_TIME = "message_log_time"  # the timeline every converted MCAP message is on


@dataclass(frozen=True)
class Chunk:
    entity: str
    static: bool
    recording_id: str
    chunk_id: bytes
    batch: pa.RecordBatch

    def column(self, name: str, kind: bytes = b"data") -> pa.Array | None:
        """The column whose `rerun:component` (data) or `rerun:index_name` (index) is `name`."""
        key = b"rerun:component" if kind == b"data" else b"rerun:index_name"
        for field, column in zip(self.batch.schema, self.batch.columns, strict=True):
            md = field.metadata or {}
            if md.get(b"rerun:kind") == kind and md.get(key, field.name.encode()) == name.encode():
                return column
        return None

    def components(self) -> list[str]:
        return [
            (f.metadata or {}).get(b"rerun:component", f.name.encode()).decode()
            for f in self.batch.schema
            if (f.metadata or {}).get(b"rerun:kind") == b"data"
        ]


def read_rrd(path: str | os.PathLike[str]) -> list[Chunk]:
    """Every chunk of the file, in file order (raises the decoder's error on a bad file)."""
    chunks = []
    for event in iter_events(path):
        if isinstance(event, ArrowMessage):
            batch = read_chunk(event)
            entity = (batch.schema.metadata or {})[b"rerun:entity_path"].decode()
            chunks.append(
                Chunk(entity, bool(event.is_static), event.store_id.recording_id, event.chunk_id or b"", batch)
            )
    return chunks


def message_counts(chunks: Sequence[Chunk]) -> dict[str, int]:
    """{entity: distinct message log times}; entities with static data only count 0."""
    times: dict[str, set[int]] = {}
    for chunk in chunks:
        seen = times.setdefault(chunk.entity, set())
        column = None if chunk.static else chunk.column(LOG_TIME, b"index")
        if column is not None:
            seen.update(column.cast(pa.int64()).to_pylist())
    return {entity: len(seen) for entity, seen in sorted(times.items())}


def values(chunks: Sequence[Chunk], entity: str, component: str) -> list[list[Any]]:
    """The non-null rows of `component` on `entity`, ordered by log time (temporal chunks only)."""
    rows: list[tuple[int, list[Any]]] = []
    for chunk in chunks:
        if chunk.entity != entity or chunk.static:
            continue
        data, times = chunk.column(component), chunk.column(LOG_TIME, b"index")
        if data is None or times is None:
            continue
        for t, row in zip(times.cast(pa.int64()).to_pylist(), data.to_pylist(), strict=True):
            if row is not None:
                rows.append((t, row))
    rows.sort(key=lambda r: r[0])
    return [row for _, row in rows]


def static_values(chunks: Sequence[Chunk], entity: str, component: str) -> list[Any]:
    """The rows of a static `component` on `entity` (e.g. `/__mcap_metadata`'s `foxglove`)."""
    found: list[Any] = []
    for chunk in chunks:
        column = chunk.column(component) if chunk.entity == entity and chunk.static else None
        if column is not None:
            found += column.to_pylist()
    return found
