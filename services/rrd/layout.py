"""Chunk layouts: what each column of a chunk schema is, worked out once per distinct schema.

A recording repeats a handful of chunk schemas (one or a few per entity) that differ only in the
chunk id stored in the schema metadata. Indexing tens of thousands of small chunks is dominated by
per-chunk Arrow overhead, so the layout (column roles, timelines, components, and where each
column's nodes and buffers sit in an IPC record batch) is cached by the schema message with the
chunk id blanked, and the record batch header is read directly (Arrow IPC flatbuffers) to get the
row count and the index values. Anything unusual (nulls in an index, IPC buffer compression,
types whose buffers are not counted here, any inconsistency) falls back to reading with pyarrow.
"""

from __future__ import annotations

import operator
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import pyarrow as pa

from services.rrd import conformance, errors, migrations
from services.rrd.lz4_prefix import PrefixTooShort
from services.rrd.migrations import migrate_field_metadata, migrate_schema_metadata, sorbet_version

if TYPE_CHECKING:
    from services.rrd.batch_plan import BatchPlan

ENTITY_PATH_KEY = migrations.ENTITY_PATH  # the keys migrations write, read here
ARCHETYPE_KEY = migrations.ARCHETYPE
COMPONENT_KEY = migrations.COMPONENT
COMPONENT_TYPE_KEY = migrations.COMPONENT_TYPE
KIND_KEY = b"rerun:kind"
INDEX_NAME_KEY = b"rerun:index_name"
IS_SORTED_KEY = b"rerun:is_sorted"

# Rerun accepts both the current and the legacy names of column kinds.
_CONTROL_KINDS = (b"control", b"row_id")
_INDEX_KINDS = (b"index", b"time")
_TIMELINE_TYPES = {"int64": "sequence", "timestamp": "timestamp", "duration": "duration"}


def timeline_type(arrow_type: pa.DataType) -> str | None:
    """sequence | timestamp | duration for an index column's Arrow type (None: not an index type)."""
    return _TIMELINE_TYPES.get(str(arrow_type).split("[")[0])


_CONTINUATION = b"\xff\xff\xff\xff"
_RECORD_BATCH = 3  # flatbuffers MessageHeader union tag
_MAX_LAYOUTS = 4096


@dataclass(frozen=True, slots=True)
class IndexColumn:
    position: int  # column position in the schema
    name: str  # timeline name
    type: str  # sequence | timestamp | duration
    is_sorted: bool
    field: pa.Field
    node: int  # its FieldNode in a record batch
    data_buffer: int  # its values buffer in a record batch


@dataclass(frozen=True, slots=True)
class DataColumn:
    position: int
    column: str  # the chunk's column name (the migrated component's when Rerun renames it)
    component: str
    archetype: str | None
    component_type: str | None
    field: pa.Field
    node: int
    buffer: int = -1  # its first buffer in a record batch

    @property
    def descriptor(self) -> tuple[str, str, str]:
        return (self.archetype or "", self.component, self.component_type or "")


@dataclass(frozen=True, slots=True)
class ChunkLayout:
    entity_path: str
    schema: pa.Schema
    row_id_field: pa.Field | None
    indexes: tuple[IndexColumn, ...]
    data: tuple[DataColumn, ...]
    top_nodes: tuple[int, ...]
    num_nodes: int
    num_buffers: int
    direct: bool  # record batches of this schema can be read without pyarrow
    archetypes: frozenset[str]
    component_names: frozenset[str]
    # From a record batch's flat node / buffer tuples: top-level lengths, the null counts of the
    # index and data columns, and (offset, length) of each index column's values buffer.
    pick_top_lengths: Callable[[tuple[int, ...]], tuple[int, ...]]
    pick_null_counts: Callable[[tuple[int, ...]], tuple[int, ...]]
    pick_index_buffers: Callable[[tuple[int, ...]], tuple[int, ...]]
    # Null counts of the columns declared non-nullable (Rerun refuses a chunk with nulls there).
    pick_required_null_counts: Callable[[tuple[int, ...]], tuple[int, ...]]
    required: tuple[int, ...]  # positions of the columns declared non-nullable
    problem: str | None  # why Rerun would refuse every chunk of this schema (None: nothing found)
    reads_values: bool  # the server reads the values of some component of these chunks
    batch_templates: list[BatchTemplate] = field(default_factory=list)  # filled by the first batch read
    # What each distinct record batch header of this layout says (`batch_plan`): a stream's
    # one-row chunks of one entity have byte-identical headers (None: read with pyarrow).
    batch_plans: dict[bytes, BatchPlan | None] = field(default_factory=dict)


def _counts(t: pa.DataType) -> tuple[int, int] | None:
    """(field nodes, buffers) a column of type `t` takes in an IPC record batch; None if not counted here."""
    if pa.types.is_null(t):
        return 1, 0
    if (
        pa.types.is_boolean(t)
        or pa.types.is_integer(t)
        or pa.types.is_floating(t)
        or pa.types.is_temporal(t)
        or pa.types.is_fixed_size_binary(t)
        or pa.types.is_decimal(t)
    ):
        return 1, 2
    if pa.types.is_string(t) or pa.types.is_binary(t) or pa.types.is_large_string(t) or pa.types.is_large_binary(t):
        return 1, 3
    if pa.types.is_map(t):
        child = _counts(pa.struct([t.key_field, t.item_field]))
        return None if child is None else (1 + child[0], 2 + child[1])
    if pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_fixed_size_list(t):
        child = _counts(t.value_type)
        own = 1 if pa.types.is_fixed_size_list(t) else 2
        return None if child is None else (1 + child[0], own + child[1])
    if pa.types.is_struct(t):
        nodes, buffers = 1, 1
        for i in range(t.num_fields):
            child = _counts(t.field(i).type)
            if child is None:
                return None
            nodes, buffers = nodes + child[0], buffers + child[1]
        return nodes, buffers
    return None


def build_layout(schema: pa.Schema, offset: int) -> ChunkLayout:
    """The layout of a chunk schema; raises NotAChunkError if it is not a Rerun chunk schema.

    Roles, entity path and descriptors are read as the newest Rerun reads them, after its
    migrations (chunks of older SDKs); columns Rerun drops (indicators) are left out of `data`."""
    version = sorbet_version(schema.metadata or {})
    metadata = migrate_schema_metadata(schema.metadata or {}, version)
    if ENTITY_PATH_KEY not in metadata:
        raise errors.NotAChunkError("Arrow schema has no rerun:entity_path metadata", offset)
    row_id_field = None
    indexes: list[IndexColumn] = []
    data: list[DataColumn] = []
    top_nodes: list[int] = []
    nodes = buffers = 0
    direct = True
    for position, fld in enumerate(schema):
        counts = _counts(fld.type)
        direct = direct and counts is not None
        fmeta = migrate_field_metadata(fld.name, fld.metadata or {}, version)
        kind = fmeta.get(KIND_KEY) if fmeta is not None else None
        if fmeta is None:
            pass  # a column the reading Rerun drops: counted for the batch layout, not a component
        elif kind in _CONTROL_KINDS:
            row_id_field = fld.with_metadata(fmeta)  # under the keys the reading Rerun uses
        elif kind in _INDEX_KINDS:
            type_name = timeline_type(fld.type)
            if type_name is None:
                raise errors.NotAChunkError(f"index column {fld.name!r} has unsupported type {fld.type}", offset)
            name = fmeta.get(INDEX_NAME_KEY, fld.name.encode()).decode()
            indexes.append(
                IndexColumn(position, name, type_name, fmeta.get(IS_SORTED_KEY) == b"true", fld, nodes, buffers + 1)
            )
        else:
            archetype = fmeta.get(ARCHETYPE_KEY)
            component_type = fmeta.get(COMPONENT_TYPE_KEY)
            component = fmeta.get(COMPONENT_KEY, fld.name.encode()).decode()
            # Named after the migrated descriptor when Rerun renames it, as the reading Rerun names it.
            migrated = component != (fld.metadata or {}).get(COMPONENT_KEY, b"").decode()
            data.append(
                DataColumn(
                    position,
                    component if migrated else fld.name,
                    component,
                    archetype.decode() if archetype else None,
                    component_type.decode() if component_type else None,
                    fld,
                    nodes,
                    buffers,
                )
            )
        top_nodes.append(nodes)
        if counts is not None:
            nodes, buffers = nodes + counts[0], buffers + counts[1]
    required = tuple(i for i, fld in enumerate(schema) if not fld.nullable)
    component_names = frozenset(c.component for c in data)
    return ChunkLayout(
        metadata[ENTITY_PATH_KEY].decode(),
        schema,
        row_id_field,
        tuple(indexes),
        tuple(data),
        tuple(top_nodes),
        nodes,
        buffers,
        direct,
        frozenset(c.archetype for c in data if c.archetype),
        component_names,
        _picker([2 * n for n in top_nodes]),
        _picker([2 * ix.node + 1 for ix in indexes] + [2 * c.node + 1 for c in data]),
        _picker([i for ix in indexes for i in (2 * ix.data_buffer, 2 * ix.data_buffer + 1)]),
        _picker([2 * top_nodes[i] + 1 for i in required]) if direct else _picker([]),
        required,
        conformance.schema_problem(
            schema, row_id_field, [(c.column, c.component, c.field.type, c.component_type) for c in data]
        ),
        conformance.reads_values(component_names),
    )


def _picker(positions: list[int]) -> Callable[[tuple[int, ...]], tuple[int, ...]]:
    """A function taking those positions of a tuple, always as a tuple (itemgetter runs in C)."""
    if not positions:
        return lambda _: ()
    if len(positions) == 1:
        (only,) = positions
        return lambda values: (values[only],)
    return operator.itemgetter(*positions)


class LayoutCache:
    """Layouts by schema message (chunk id and volatile values blanked); bounded, cleared when full."""

    def __init__(self, max_size: int = _MAX_LAYOUTS) -> None:
        self._layouts: dict[bytes, ChunkLayout] = {}
        self._max_size = max_size
        # Where the volatile values sat in schema messages of each length seen lately. A message cut
        # where another's were, whose key is then a known layout's, equals that message outside
        # those spans: its flatbuffers (all outside them) are the same, so its values sit there too.
        # Reading them from the flatbuffers costs several times the cut.
        self._cuts: dict[int, list[Spans]] = {}

    def get(self, schema_message: bytes, chunk_id_text: bytes, offset: int) -> ChunkLayout:
        volatile = _VOLATILE_KEY in schema_message
        if volatile:
            for spans in self._cuts.get(len(schema_message), ()):
                found = self._layouts.get(_without_id(_cut(schema_message, spans), chunk_id_text))
                if found is not None:
                    return found
        key = _without_id(self._cut_volatile(schema_message) if volatile else schema_message, chunk_id_text)
        layout = self._layouts.get(key)
        if layout is None:
            try:
                schema = pa.ipc.read_schema(
                    pa.py_buffer(_CONTINUATION + struct.pack("<i", len(schema_message)) + schema_message)
                )
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError, OSError, TypeError, EOFError) as exc:
                raise errors.NotAChunkError(f"payload is not an Arrow IPC stream ({exc})", offset) from exc
            layout = build_layout(schema, offset)
            if len(self._layouts) >= self._max_size:
                self._layouts.clear()
            self._layouts[key] = layout
        return layout

    def _cut_volatile(self, schema_message: bytes) -> bytes:
        spans = volatile_spans(schema_message)
        if spans:
            if len(self._cuts) >= self._max_size:
                self._cuts.clear()
            known = self._cuts.setdefault(len(schema_message), [])
            if spans not in known:
                known.insert(0, spans)
                del known[_CUTS_PER_LENGTH:]
        return _cut(schema_message, spans)


# Schema metadata whose value differs from chunk to chunk of one schema, like the chunk id: the SDK
# stamps every chunk it sends over gRPC (not those it writes to a file) with when it encoded and sent
# it (`rerun:timestamp_sdk_ipc_encoded`, `rerun:timestamp_sdk_grpc_sink`: "SECONDS.NANOSECONDS").
_VOLATILE_KEY = b"rerun:timestamp_"
_CUTS_PER_LENGTH = 4

Spans = tuple[tuple[int, int], ...]


def _without_id(key: bytes, chunk_id_text: bytes) -> bytes:
    return key.replace(chunk_id_text, b"") if chunk_id_text else key


def volatile_spans(schema_message: bytes) -> Spans:
    """Where the values of volatile metadata entries sit, in order. Reads the flatbuffers: Message 2
    header (Schema); Schema 2 custom_metadata, a vector of KeyValue (0 key, 1 value). Unreadable:
    none."""
    try:
        return tuple(sorted(_volatile_spans(schema_message)))
    except (struct.error, IndexError, UnicodeDecodeError):
        return ()


def _cut(message: bytes, spans: Spans) -> bytes:
    """`message` without the bytes of `spans` (a cache key: one layout per schema, not per chunk)."""
    if not spans:
        return message
    out, at = [], 0
    for start, end in spans:
        out.append(message[at:start])
        at = end
    out.append(message[at:])
    return b"".join(out)


def _volatile_spans(msg: bytes) -> list[tuple[int, int]]:
    schema = _table_field(msg, _U32.unpack_from(msg, 0)[0], 2)
    vector = _table_field(msg, schema, 2) if schema is not None else None
    if vector is None:
        return []
    spans = []
    for i in range(_U32.unpack_from(msg, vector)[0]):
        slot = vector + 4 + 4 * i
        pair = slot + _U32.unpack_from(msg, slot)[0]
        key, value = _table_field(msg, pair, 0), _table_field(msg, pair, 1)
        if key is not None and value is not None and _string(msg, key).startswith(_VOLATILE_KEY):
            spans.append((value + 4, value + 4 + _U32.unpack_from(msg, value)[0]))
    return spans


def _table_field(msg: bytes, table: int, slot: int) -> int | None:
    """Where the object an offset field of a flatbuffers table points to starts, or None if unset."""
    vtable = table - _I32.unpack_from(msg, table)[0]
    if _U16.unpack_from(msg, vtable)[0] < 6 + 2 * slot:
        return None
    field_offset = _U16.unpack_from(msg, vtable + 4 + 2 * slot)[0]
    if not field_offset:
        return None
    at: int = table + field_offset
    target: int = at + _U32.unpack_from(msg, at)[0]
    return target


def _string(msg: bytes, at: int) -> bytes:
    length = _U32.unpack_from(msg, at)[0]
    if at + 4 + length > len(msg):
        raise IndexError("string past the end of the message")
    return msg[at + 4 : at + 4 + length]


def split_ipc(data: bytes, total: int | None = None) -> tuple[bytes, int] | None:
    """(schema message flatbuffer, position of the next message) of an IPC stream, or None.
    `data` may be the first bytes of a payload of `total` bytes (PrefixTooShort if the schema
    message does not end within them)."""
    if len(data) < 8 or data[:4] != _CONTINUATION:
        return None
    (size,) = struct.unpack_from("<i", data, 4)
    if size <= 0 or 8 + size > (len(data) if total is None else total):
        return None
    if 8 + size > len(data):
        raise PrefixTooShort(8 + size)
    return data[8 : 8 + size], 8 + size


@dataclass(slots=True)
class BatchHeader:
    length: int
    nodes: tuple[int, ...]  # flat (length, null_count) pairs
    buffers: tuple[int, ...]  # flat (offset, length) pairs
    body: int  # position of the body in the data
    end: int = 0  # position of the end of the body


_I32 = struct.Struct("<i")
_U32 = struct.Struct("<I")
_U16 = struct.Struct("<H")
_I64 = struct.Struct("<q")


def read_batch_header(data: bytes, pos: int, layout: ChunkLayout, total: int | None = None) -> BatchHeader | None:
    """The record batch header at `pos`, if it is a plain one matching `layout`; else None.
    `data` may be the first bytes of a payload of `total` bytes, as long as they hold the header."""
    templates = layout.batch_templates
    if templates:
        header = templates[0].match(data, pos, total)
        if header is not None:
            return header
    try:
        parsed = _parse_batch_header(data, pos, layout, total)
    except (struct.error, IndexError):
        return None
    if parsed is None:
        return None
    header, template = parsed
    if template is not None and not templates:
        templates.append(template)
    return header


def _checked_header(
    total: int, length: int, body_length: int, nodes: tuple[int, ...], buffers: tuple[int, ...], body: int
) -> BatchHeader | None:
    if length < 0 or body_length < 0 or body + body_length > total:
        return None
    if buffers and (min(buffers) < 0 or max(map(operator.add, buffers[::2], buffers[1::2])) > body_length):
        return None
    return BatchHeader(length, nodes, buffers, body, body + body_length)


def _parse_batch_header(
    data: bytes, pos: int, layout: ChunkLayout, total: int | None = None
) -> tuple[BatchHeader | None, BatchTemplate | None] | None:
    """Reads the IPC flatbuffers (Message: 1 header_type, 2 header, 3 bodyLength; RecordBatch:
    0 length, 1 nodes, 2 buffers, 3 compression) and notes where the values sit, as a template."""
    if data[pos : pos + 4] != _CONTINUATION:
        return None
    size = _I32.unpack_from(data, pos + 4)[0]
    base = pos + 8
    body = base + size
    total = len(data) if total is None else total
    if size <= 0 or body > total:
        return None
    if body > len(data):
        raise PrefixTooShort(body)
    message = base + _U32.unpack_from(data, base)[0]
    vtable = message - _I32.unpack_from(data, message)[0]
    if _U16.unpack_from(data, vtable)[0] < 12:
        return None
    o_type, o_header, o_body = struct.unpack_from("<3H", data, vtable + 6)
    if not o_type or not o_header or not o_body or data[message + o_type] != _RECORD_BATCH:
        return None
    body_length = _I64.unpack_from(data, message + o_body)[0]
    at = message + o_header
    batch = at + _U32.unpack_from(data, at)[0]
    vtable = batch - _I32.unpack_from(data, batch)[0]
    slots = (_U16.unpack_from(data, vtable)[0] - 4) // 2
    if slots < 3:
        return None
    o_length, o_nodes, o_buffers = struct.unpack_from("<3H", data, vtable + 4)
    if slots > 3 and _U16.unpack_from(data, vtable + 10)[0]:
        return None  # IPC buffer compression: not used by Rerun
    if not o_length:
        return None
    length = _I64.unpack_from(data, batch + o_length)[0]
    nodes = _struct_vector(data, batch, o_nodes, layout.num_nodes)
    buffers = _struct_vector(data, batch, o_buffers, layout.num_buffers)
    if nodes is None or buffers is None:
        return None
    header = _checked_header(total, length, body_length, nodes[0], buffers[0], body)
    values = [
        (batch + o_length - base, 8),
        (message + o_body - base, 8),
        (nodes[1] - base, 16 * layout.num_nodes),
        (buffers[1] - base, 16 * layout.num_buffers),
    ]
    return header, BatchTemplate.build(data, pos, size, values, layout)


def _struct_vector(data: bytes, table: int, field_offset: int, expected: int) -> tuple[tuple[int, ...], int] | None:
    """A flatbuffers vector of 16-byte (int64, int64) structs as a flat tuple, if it has `expected`
    items, and where its items start."""
    if not field_offset:
        return None
    at = table + field_offset
    vector = at + _U32.unpack_from(data, at)[0]
    if _U32.unpack_from(data, vector)[0] != expected:
        return None
    return struct.unpack_from(f"<{2 * expected}q", data, vector + 4), vector + 4


@dataclass(slots=True)
class BatchTemplate:
    """A record batch header of a layout with its values blanked: any header whose other bytes are
    identical has its values at the same places (flatbuffers navigation only reads those bytes)."""

    prefix: bytes  # continuation marker and metadata size
    size: int  # metadata size
    gaps: tuple[tuple[int, int, bytes], ...]  # (start, end, bytes) outside the values
    at_length: int
    at_body_length: int
    at_nodes: int
    at_buffers: int
    nodes_format: struct.Struct
    buffers_format: struct.Struct

    @classmethod
    def build(
        cls, data: bytes, pos: int, size: int, values: list[tuple[int, int]], layout: ChunkLayout
    ) -> BatchTemplate | None:
        """`values`: (start, length) in the metadata of length, bodyLength, nodes, buffers."""
        base, gaps, cursor = pos + 8, [], 0
        for start, length in sorted(values):
            if start < cursor or start + length > size:
                return None  # overlapping or out of the metadata: do not template
            if start > cursor:
                gaps.append((cursor, start, bytes(data[base + cursor : base + start])))
            cursor = start + length
        if cursor < size:
            gaps.append((cursor, size, bytes(data[base + cursor : base + size])))
        (at_length, _), (at_body, _), (at_nodes, _), (at_buffers, _) = values
        return cls(
            bytes(data[pos:base]),
            size,
            tuple(gaps),
            at_length,
            at_body,
            at_nodes,
            at_buffers,
            struct.Struct(f"<{2 * layout.num_nodes}q"),
            struct.Struct(f"<{2 * layout.num_buffers}q"),
        )

    def match(self, data: bytes, pos: int, total: int | None = None) -> BatchHeader | None:
        base = pos + 8
        if data[pos:base] != self.prefix:
            return None
        total = len(data) if total is None else total
        if base + self.size > len(data):
            if base + self.size > total:
                return None
            raise PrefixTooShort(base + self.size)
        for start, end, expected in self.gaps:
            if data[base + start : base + end] != expected:
                return None
        return _checked_header(
            total,
            _I64.unpack_from(data, base + self.at_length)[0],
            _I64.unpack_from(data, base + self.at_body_length)[0],
            self.nodes_format.unpack_from(data, base + self.at_nodes),
            self.buffers_format.unpack_from(data, base + self.at_buffers),
            base + self.size,
        )
