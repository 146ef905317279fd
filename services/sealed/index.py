"""`chunks.parquet`: the index of a sealed run, one row per message of its `recording.rrd`
(rows: `services.rrd.chunk_index`, shared with the hot index).

Every chunk has a row (id, entity, static, rows, per-timeline min/max, components, byte offset
and length of its whole frame, and per component and timeline the min/max/count of its non-null
rows, which a latest-at query needs for sparse components); so do the few other messages (store infos, blueprint
activations), so that a reader can rebuild a filtered stream from ranged reads alone, in the
recording's own order. The table is readable as is by DuckDB, Polars or Spark.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, overload

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from core.errors import InternalError
from services.rrd.chunk_index import (
    BLUEPRINT_ACTIVATION,
    CHUNK,
    STORE_INFO,
    ComponentRange,
    IndexRow,
    IndexRows,
    TimelineRange,
    component_ranges,
)
from services.runtime import collection_paused

__all__ = [
    "BLUEPRINT_ACTIVATION",
    "CHUNK",
    "STORE_INFO",
    "ComponentRange",
    "IndexRow",
    "IndexTable",
    "TimelineRange",
    "chunk_ids_of",
    "component_ranges",
    "from_parquet",
    "read_index",
    "to_parquet",
]

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
    return read_index(data).all()


def read_index(data: bytes) -> IndexTable:
    """A `chunks.parquet` as read: its columns, rows made when asked for (`IndexTable`)."""
    try:
        table = pq.ParquetFile(io.BytesIO(data)).read()
        if "component_ranges" not in table.column_names:  # written before the column existed
            table = table.append_column(
                "component_ranges", pa.nulls(table.num_rows, SCHEMA.field("component_ranges").type)
            )
        table = table.select(SCHEMA.names).cast(SCHEMA).combine_chunks()
    except (pa.ArrowException, ValueError) as exc:
        raise InternalError(f"chunks.parquet is unreadable ({exc}): re-seal the run from its recording") from exc
    return IndexTable(table)


class IndexTable(Sequence[IndexRow]):
    """A sealed run's chunk index as its columns, each row made into an `IndexRow` only when asked
    for. A window of one entity needs the rows of that entity's chunks and the few other messages:
    at 50 GB a few thousand of tens of thousands, so its first byte no longer waits for every row
    to be made (5 us each). Which rows a window needs, the run's timelines and entities are worked
    out from the columns. Iterating makes every row, once; `derived` keeps what readers work out
    from the rows, as `IndexRows.derived` does."""

    def __init__(self, table: pa.Table) -> None:
        self._table = table
        self._made: dict[int, IndexRow] = {}
        self._all: IndexRows | None = None
        self.derived: dict[str, Any] = {}

    def __len__(self) -> int:
        return int(self._table.num_rows)

    @overload
    def __getitem__(self, index: int) -> IndexRow: ...
    @overload
    def __getitem__(self, index: slice) -> list[IndexRow]: ...
    def __getitem__(self, index: int | slice) -> IndexRow | list[IndexRow]:
        if isinstance(index, slice):
            return self.at(range(len(self))[index])
        return self.at([index if index >= 0 else len(self) + index])[0]

    def __iter__(self) -> Iterator[IndexRow]:
        return iter(self.all())

    @property
    def rows_made(self) -> int:
        """How many rows have been made so far."""
        return len(self._all) if self._all is not None else len(self._made)

    def all(self) -> IndexRows:
        """Every row, in file order (made once)."""
        if self._all is None:
            with collection_paused():  # the garbage collector's passes were 40 % of the parse
                self._all = IndexRows(_rows(self._table))
            self._made = {}
        return self._all

    def at(self, positions: Iterable[int]) -> list[IndexRow]:
        """The rows at `positions`, in that order; those not made yet are made together."""
        positions = list(positions)
        every, made = self._all, self._made  # (another thread's `all()` may replace both meanwhile)
        if every is not None:
            return [every[i] for i in positions]
        missing = sorted({i for i in positions if i not in made})
        if missing:
            with collection_paused():
                rows = _rows(self._table.take(pa.array(missing, pa.int64())))
            made.update(zip(missing, rows, strict=True))
        return [made[i] for i in positions]

    def groups(self) -> tuple[dict[str, list[int]], list[int], list[int]]:
        """Positions of the recording's chunks by entity (each in file order), of the blueprint's
        chunks, and of every row that is not a chunk."""
        column = self._table.column
        chunk = flags(pc.equal(column("kind"), CHUNK))
        recording = flags(pc.equal(column("store_kind"), "recording"))
        positions = np.arange(len(self))
        entities = pc.dictionary_encode(pc.fill_null(one_array(column("entity_path")), ""))
        codes = entities.indices.to_numpy()
        names = entities.dictionary.to_pylist()
        chosen = chunk & recording
        order = np.argsort(codes[chosen], kind="stable")  # by entity, each in file order
        ranked, ranked_codes = positions[chosen][order], codes[chosen][order]
        cuts = np.flatnonzero(np.diff(ranked_codes)) + 1
        by_entity = {
            names[group_codes[0]]: group.tolist()
            for group, group_codes in zip(np.split(ranked, cuts), np.split(ranked_codes, cuts), strict=True)
            if len(group)
        }
        return by_entity, positions[chunk & ~recording].tolist(), positions[~chunk].tolist()

    def columns(self, positions: list[int], names: Sequence[str] | None = None) -> pa.Table:
        """The rows at `positions` as columns (`names`, or all), without making them."""
        table = self._table if names is None else self._table.select(list(names))
        return table.take(pa.array(positions, pa.int64()))

    def timeline_types(self) -> dict[str, str]:
        """Each timeline of the run's chunks and its type."""
        timelines = one_array(self._of_chunks("timelines"))
        flat = timelines.flatten()
        if not len(flat):
            return {}
        pairs = pa.table({"name": flat.field("name"), "type": flat.field("type")}).group_by(["name", "type"])
        found = pairs.aggregate([])
        return dict(zip(found.column("name").to_pylist(), found.column("type").to_pylist(), strict=True))

    def entity_paths(self) -> set[str]:
        """The entities of the run's chunks."""
        return {p for p in pc.unique(self._of_chunks("entity_path")).to_pylist() if p}

    def _of_chunks(self, name: str) -> pa.ChunkedArray:
        """One column's values of the chunks' rows (not store infos or blueprint activations): the
        other columns are not copied."""
        return pc.filter(self._table.column(name), pc.equal(self._table.column("kind"), CHUNK))


def flags(values: pa.ChunkedArray | pa.Array) -> Any:
    """A boolean column as a numpy array (null: False); for readers of the index's columns too."""
    return one_array(pc.fill_null(values, False)).to_numpy(zero_copy_only=False)


def _rows(table: pa.Table) -> list[IndexRow]:
    # Column by column, the nested ones flattened once and cut per row: a run of 50 GB has tens of
    # thousands of rows, and a window's first byte waits for them (row dicts took 60 us a row).
    column = table.column
    timelines = _per_row(
        column("timelines"), lambda v: map(TimelineRange._make, zip(*_fields(v, _TIMELINE), strict=True))
    )
    components = _per_row(column("components"), _values)
    ranges = _per_row(
        column("component_ranges"), lambda v: map(ComponentRange._make, zip(*_fields(v, _COMPONENT_RANGE), strict=True))
    )
    flat = zip(*(_values(column(name)) for name in _FLAT), strict=True)
    return [
        IndexRow(
            kind=kind,
            store_kind=store_kind,
            offset=offset,
            length=length,
            chunk_id=bytes.fromhex(chunk_id) if chunk_id else None,
            entity_path=entity_path,
            is_static=bool(is_static),
            num_rows=num_rows or 0,
            timelines=row_timelines or (),
            components=row_components or (),
            component_ranges=row_ranges,
        )
        for (
            kind,
            store_kind,
            chunk_id,
            entity_path,
            is_static,
            num_rows,
            offset,
            length,
        ), row_timelines, row_components, row_ranges in zip(flat, timelines, components, ranges, strict=True)
    ]


_FLAT = ("kind", "store_kind", "chunk_id", "entity_path", "is_static", "num_rows", "offset", "length")


def _fields(values: pa.StructArray, kind: pa.StructType) -> list[list[Any]]:
    return [_values(values.field(i)) for i in range(kind.num_fields)]


def _values(values: pa.Array | pa.ChunkedArray) -> list[Any]:
    """`values.to_pylist()`, faster for the index's columns: pyarrow makes a scalar object per value
    there (a third of a microsecond each, and a run of 50 GB has hundreds of thousands), numpy's
    `tolist` does not; names (entities, components, timelines) are few, so each is made once."""
    if isinstance(values, pa.ChunkedArray):
        values = one_array(values)
    kind = values.type
    if values.null_count == 0 and (pa.types.is_integer(kind) or pa.types.is_boolean(kind)):
        return list(values.to_numpy(zero_copy_only=False).tolist())
    if pa.types.is_string(kind):  # the table was cast to SCHEMA: never large_string
        encoded = pc.dictionary_encode(values)
        if len(encoded.dictionary) * 4 < len(values):  # names, repeated: one Python string each
            names = [*encoded.dictionary.to_pylist(), None]  # index -1 (a null) -> None
            indices = pc.fill_null(encoded.indices, -1).to_numpy().tolist()
            return [names[i] for i in indices]
    return list(values.to_pylist())


def one_array(column: pa.ChunkedArray | pa.Array) -> pa.Array:
    """The column as one array (a file read in several row groups has several chunks)."""
    if not isinstance(column, pa.ChunkedArray):
        return column
    return column.combine_chunks() if column.num_chunks != 1 else column.chunk(0)


def _per_row(column: pa.ChunkedArray, make: Callable[[pa.Array], Iterable[Any]]) -> list[tuple[Any, ...] | None]:
    """A list column as one tuple per row (None where the row's list is null), its values made by
    `make` from all of the column's values at once."""
    array = one_array(column)
    assert isinstance(array, pa.ListArray)
    flat = array.flatten()  # the values of the non-null lists, in order
    made = list(make(flat)) if len(flat) else []
    lengths = _values(pc.fill_null(pc.list_value_length(array), 0))
    valid = _values(array.is_valid())
    out: list[tuple[Any, ...] | None] = []
    at = 0
    for n, ok in zip(lengths, valid, strict=True):
        out.append(tuple(made[at : at + n]) if ok else None)
        at += n
    return out


def chunk_ids_of(data: bytes) -> frozenset[bytes]:
    """The ids of the chunks a `chunks.parquet` lists, read from its two columns that say so (a
    fraction of what `from_parquet` decodes)."""
    try:
        table = pq.read_table(io.BytesIO(data), columns=["kind", "chunk_id"])
    except (pa.ArrowException, ValueError) as exc:
        raise InternalError(f"chunks.parquet is unreadable ({exc}): re-seal the run from its recording") from exc
    kinds, ids = table.column("kind").to_pylist(), table.column("chunk_id").to_pylist()
    return frozenset(
        bytes.fromhex(chunk_id) for kind, chunk_id in zip(kinds, ids, strict=True) if kind == CHUNK and chunk_id
    )
