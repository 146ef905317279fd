"""One row of a run's chunk index: where a message sits in the run's recording and, for a chunk,
what it holds (entity, static, rows, per-timeline min/max, components and where each one's
non-null rows lie).

The same rows index a sealed run (`chunks.parquet`) and a hot run (the index kept beside its hot
file), so whoever selects chunks (downloads, the catalog server) treats both alike.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, NamedTuple

from services.rrd.chunk import ChunkMeta
from services.rrd.messages import StoreKind

CHUNK = "chunk"
STORE_INFO = "store_info"
BLUEPRINT_ACTIVATION = "blueprint_activation"


# Named tuples, not frozen dataclasses: a big run's index holds hundreds of thousands of them, and a
# window's first byte waits for them to be made (a tuple is made in a third of the time).
class TimelineRange(NamedTuple):
    name: str
    type: str
    min: int
    max: int


class ComponentRange(NamedTuple):
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
    offset: int  # of the message's frame header in the recording
    length: int  # of the whole frame (header and payload)
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


class IndexRows(list[IndexRow]):
    """A run's index rows, in file order, with what readers work out from them once (`derived`, by
    a key each reader owns), kept as long as the rows are: a sealed run's parsed index is cached
    and asked for window after window, and planning one goes over every row."""

    def __init__(self, rows: Iterable[IndexRow] = ()) -> None:
        super().__init__(rows)
        self.derived: dict[str, Any] = {}


def store_kind_name(kind: StoreKind) -> str:
    """The `store_kind` of a row: "blueprint", else "recording"."""
    return "blueprint" if kind == StoreKind.BLUEPRINT else "recording"


def chunk_row(store_kind: str, offset: int, length: int, meta: ChunkMeta) -> IndexRow:
    """The row of a chunk whose frame is `length` bytes at `offset`."""
    return IndexRow(
        CHUNK,
        store_kind,
        offset,
        length,
        meta.chunk_id,
        meta.entity_path,
        meta.is_static,
        meta.num_rows,
        tuple(TimelineRange(t.name, t.type, t.range.min, t.range.max) for t in meta.timelines),
        tuple(sorted(meta.component_names)),
        component_ranges(meta),
    )
