"""`chunks.parquet`: the index of a sealed run, one row per message of its `recording.rrd`.

Every chunk has a row (id, entity, static, rows, per-timeline min/max, components, byte offset
and length of its whole frame, and per component and timeline the min/max/count of its non-null
rows, which a latest-at query needs for sparse components); so do the few other messages (store infos, blueprint
activations), so that a reader can rebuild a filtered stream from ranged reads alone, in the
recording's own order. The table is readable as is by DuckDB, Polars or Spark.
"""

from __future__ import annotations

import io
from collections.abc import Iterable
from dataclasses import dataclass

import pyarrow as pa
import pyarrow.parquet as pq

from core.errors import InternalError
from services.rrd.chunk import ChunkMeta

CHUNK = "chunk"
STORE_INFO = "store_info"
BLUEPRINT_ACTIVATION = "blueprint_activation"

_TIMELINE = pa.struct([("name", pa.string()), ("type", pa.string()), ("min", pa.int64()), ("max", pa.int64())])
_COMPONENT_RANGE = pa.struct(
    [
        ("component", pa.string()),
        ("timeline", pa.string()),
        ("min", pa.int64()),
        ("max", pa.int64()),
        ("rows", pa.int64()),
    ]
)
SCHEMA = pa.schema(
    [
        ("kind", pa.string()),  # chunk | store_info | blueprint_activation
        ("store_kind", pa.string()),  # recording | blueprint
        ("chunk_id", pa.string()),  # 32 hex digits (chunks only)
        ("entity_path", pa.string()),
        ("is_static", pa.bool_()),
        ("num_rows", pa.int64()),
        ("timelines", pa.list_(_TIMELINE)),
        ("components", pa.list_(pa.string())),
        ("offset", pa.int64()),  # of the message's frame header in recording.rrd
        ("length", pa.int64()),  # of the whole frame (header and payload)
        # per component with data: where its non-null rows lie on each timeline; null in indexes written
        # before this column existed (readers then read the chunk when they need it)
        ("component_ranges", pa.list_(_COMPONENT_RANGE)),
    ]
)


@dataclass(frozen=True)
class TimelineRange:
    name: str
    type: str
    min: int
    max: int


@dataclass(frozen=True)
class ComponentRange:
    component: str
    timeline: str
    min: int
    max: int
    rows: int  # non-null rows of the component in the chunk


def component_ranges(meta: ChunkMeta) -> tuple[ComponentRange, ...]:
    return tuple(
        ComponentRange(c.component, timeline, r.min, r.max, c.num_rows)
        for c in meta.components
        for timeline, r in c.ranges.items()
    )


@dataclass(frozen=True)
class IndexRow:
    kind: str
    store_kind: str
    offset: int
    length: int
    chunk_id: bytes | None = None
    entity_path: str | None = None
    is_static: bool = False
    num_rows: int = 0
    timelines: tuple[TimelineRange, ...] = ()
    components: tuple[str, ...] = ()
    component_ranges: tuple[ComponentRange, ...] | None = None  # None: not known (an older index)

    @property
    def end(self) -> int:
        return self.offset + self.length


def to_parquet(rows: Iterable[IndexRow]) -> bytes:
    rows = list(rows)
    table = pa.table(
        {
            "kind": [r.kind for r in rows],
            "store_kind": [r.store_kind for r in rows],
            "chunk_id": [r.chunk_id.hex() if r.chunk_id is not None else None for r in rows],
            "entity_path": [r.entity_path for r in rows],
            "is_static": [r.is_static for r in rows],
            "num_rows": [r.num_rows for r in rows],
            "timelines": [
                [{"name": t.name, "type": t.type, "min": t.min, "max": t.max} for t in r.timelines] for r in rows
            ],
            "components": [list(r.components) for r in rows],
            "offset": [r.offset for r in rows],
            "length": [r.length for r in rows],
            "component_ranges": [
                None
                if r.component_ranges is None
                else [
                    {"component": c.component, "timeline": c.timeline, "min": c.min, "max": c.max, "rows": c.rows}
                    for c in r.component_ranges
                ]
                for r in rows
            ],
        },
        schema=SCHEMA,
    )
    out = io.BytesIO()
    pq.write_table(table, out, compression="zstd")
    return out.getvalue()


def from_parquet(data: bytes) -> list[IndexRow]:
    try:
        table = pq.read_table(io.BytesIO(data))
        if "component_ranges" not in table.column_names:  # written before the column existed
            table = table.append_column(
                "component_ranges", pa.nulls(table.num_rows, SCHEMA.field("component_ranges").type)
            )
        table = table.select(SCHEMA.names).cast(SCHEMA)
    except (pa.ArrowException, ValueError) as exc:
        raise InternalError(f"chunks.parquet is unreadable ({exc}): re-seal the run from its recording") from exc
    rows = []
    for item in table.to_pylist():
        rows.append(
            IndexRow(
                kind=item["kind"],
                store_kind=item["store_kind"],
                offset=item["offset"],
                length=item["length"],
                chunk_id=bytes.fromhex(item["chunk_id"]) if item["chunk_id"] else None,
                entity_path=item["entity_path"],
                is_static=bool(item["is_static"]),
                num_rows=item["num_rows"] or 0,
                timelines=tuple(TimelineRange(**t) for t in item["timelines"] or ()),
                components=tuple(item["components"] or ()),
                component_ranges=None
                if item["component_ranges"] is None
                else tuple(ComponentRange(**c) for c in item["component_ranges"]),
            )
        )
    return rows
