"""The SHA-256 Rerun gives a recording's Sorbet schema (`sorbet_schema_sha256` of an RRD manifest).

Rerun hashes the schema's Arrow IPC encoding as its Rust Arrow library writes it (fields sorted by
name, no schema metadata, the stream writer's schema message padded to 64 bytes). Flatbuffers leave
the layout to the writer, so pyarrow's encoding of the same schema is other bytes and another hash;
this module lays the schema out as the Rust writer does (its table, vtable and padding order), which
its clients check a manifest's hash against. A type the Rust writer handles that this module does
not (decimals, views, run-end encoding) gives None: the caller hashes pyarrow's encoding instead.
"""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Sequence

import pyarrow as pa

_UOFFSET = 4
_METADATA_V5 = 4
_MESSAGE_HEADER_SCHEMA = 1
_ALIGNMENT = 64  # the Rust writer's default IPC alignment
_CONTINUATION = b"\xff\xff\xff\xff"
# Arrow's Schema.fbs: union `Type` members, and enum values
_NULL, _INT, _FLOAT, _BINARY, _UTF8, _BOOL = 1, 2, 3, 4, 5, 6
_DATE, _TIME, _TIMESTAMP, _INTERVAL, _LIST, _STRUCT, _UNION, _FIXED_BINARY, _FIXED_LIST, _MAP, _DURATION = (
    8,
    9,
    10,
    11,
    12,
    13,
    14,
    15,
    16,
    17,
    18,
)
_LARGE_BINARY, _LARGE_UTF8, _LARGE_LIST = 19, 20, 21
_UNITS = {"s": 0, "ms": 1, "us": 2, "ns": 3}
_PRECISION = {16: 0, 32: 1, 64: 2}


class Unsupported(Exception):
    """A type this layout does not cover."""


class _Builder:
    """Flatbuffers written back to front, as the Rust `FlatBufferBuilder` writes them: the same
    alignment, default elision, vtable layout and sharing, so the same calls give the same bytes."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []  # the used space, back to front
        self.used = 0
        self.min_align = 1
        self.fields: list[tuple[int, int]] = []  # (vtable slot, where the field ended) of the open table
        self.vtables: dict[bytes, int] = {}  # vtable bytes -> where it ended

    def _prepend(self, data: bytes) -> None:
        self.parts.append(data)
        self.used += len(data)

    def align(self, length: int, alignment: int) -> None:
        self.min_align = max(self.min_align, alignment)
        self._prepend(bytes((-(self.used + length)) % alignment))

    def scalar(self, fmt: str, value: int) -> int:
        size = struct.calcsize(fmt)
        self.align(size, size)
        self._prepend(struct.pack(fmt, value))
        return self.used

    def offset(self, target: int) -> int:
        self.align(_UOFFSET, _UOFFSET)
        self._prepend(struct.pack("<I", self.used + _UOFFSET - target))
        return self.used

    def string(self, text: str) -> int:
        data = text.encode()
        self.align(len(data) + 1, _UOFFSET)
        self._prepend(data + b"\0")
        return self.scalar("<I", len(data))

    def offsets(self, targets: Sequence[int]) -> int:
        size = _UOFFSET * len(targets)
        self.align(size, _UOFFSET)
        end = self.used + size
        self._prepend(b"".join(struct.pack("<I", end - i * _UOFFSET - t) for i, t in enumerate(targets)))
        return self.scalar("<I", len(targets))

    def int32s(self, values: Sequence[int]) -> int:
        self.align(4 * len(values), _UOFFSET)
        self._prepend(b"".join(struct.pack("<i", v) for v in values))
        return self.scalar("<I", len(values))

    # --- tables -----------------------------------------------------------------------------

    def start(self) -> int:
        self.fields = []
        return self.used

    def slot(self, slot: int, fmt: str, value: int, default: int) -> None:
        if value != default:
            self.fields.append((slot, self.scalar(fmt, value)))

    def slot_offset(self, slot: int, target: int) -> None:
        self.fields.append((slot, self.offset(target)))

    def end(self, tail: int) -> int:
        """Close the table: its offset to its vtable, and the vtable unless an identical one was
        written before (the Rust builder writes it, finds the twin, and takes it back)."""
        self.align(_UOFFSET, _UOFFSET)
        table = self.used + _UOFFSET
        length = max((s for s, _ in self.fields), default=2) + 2
        vtable = bytearray(length)
        struct.pack_into("<HH", vtable, 0, length, table - tail)
        for slot, end in self.fields:
            struct.pack_into("<H", vtable, slot, table - end)
        key = bytes(vtable)
        where = self.vtables.get(key)
        self._prepend(struct.pack("<i", (where if where is not None else table + length) - table))
        if where is None:
            self._prepend(key)
            self.vtables[key] = self.used
        self.fields = []
        return table

    def empty_table(self) -> int:
        return self.end(self.start())

    def finish(self, root: int) -> bytes:
        self.align(_UOFFSET, self.min_align)
        self.offset(root)
        return b"".join(reversed(self.parts))


def _metadata(b: _Builder, metadata: dict[bytes, bytes]) -> int:
    pairs = []
    for key in sorted(metadata, key=lambda k: k.decode()):
        name, value = b.string(key.decode()), b.string(metadata[key].decode())
        tail = b.start()
        b.slot_offset(4, name)
        b.slot_offset(6, value)
        pairs.append(b.end(tail))
    return b.offsets(pairs)


def _field(b: _Builder, field: pa.Field) -> int:
    metadata = _metadata(b, field.metadata) if field.metadata else None
    name = b.string(field.name)
    type_type, type_table, children = _type(b, field.type)
    tail = b.start()
    b.slot_offset(4, name)
    b.slot(8, "<B", type_type, 0)
    b.slot(6, "<B", int(field.nullable), 0)
    b.slot_offset(14, children)
    b.slot_offset(10, type_table)
    if metadata is not None:
        b.slot_offset(16, metadata)
    return b.end(tail)


def _scalar_table(b: _Builder, slots: Sequence[tuple[int, str, int, int]]) -> int:
    tail = b.start()
    for slot, fmt, value, default in slots:
        b.slot(slot, fmt, value, default)
    return b.end(tail)


def _type(b: _Builder, t: pa.DataType) -> tuple[int, int, int]:
    """(union tag, type table, children vector) of a field's type, built in the Rust writer's order."""
    if pa.types.is_integer(t):
        children = b.offsets([])
        table = _scalar_table(b, [(6, "<B", int(pa.types.is_signed_integer(t)), 0), (4, "<i", t.bit_width, 0)])
        return _INT, table, children
    if pa.types.is_floating(t):
        children = b.offsets([])
        return _FLOAT, _scalar_table(b, [(4, "<h", _PRECISION[t.bit_width], 0)]), children
    if pa.types.is_timestamp(t):
        zone = b.string(t.tz or "")
        tail = b.start()
        b.slot(4, "<h", _UNITS[t.unit], 0)
        if t.tz:
            b.slot_offset(6, zone)
        return _TIMESTAMP, b.end(tail), b.offsets([])
    if pa.types.is_duration(t):
        return _DURATION, _scalar_table(b, [(4, "<h", _UNITS[t.unit], 1)]), b.offsets([])
    if pa.types.is_date(t):
        return _DATE, _scalar_table(b, [(4, "<h", 0 if pa.types.is_date32(t) else 1, 1)]), b.offsets([])
    if pa.types.is_time(t):
        table = _scalar_table(b, [(6, "<i", t.bit_width, 32), (4, "<h", _UNITS[t.unit], 1)])
        return _TIME, table, b.offsets([])
    if pa.types.is_fixed_size_binary(t):
        return _FIXED_BINARY, _scalar_table(b, [(4, "<i", t.byte_width, 0)]), b.offsets([])
    simple = {
        pa.types.is_null: _NULL,
        pa.types.is_boolean: _BOOL,
        pa.types.is_binary: _BINARY,
        pa.types.is_large_binary: _LARGE_BINARY,
        pa.types.is_string: _UTF8,
        pa.types.is_large_string: _LARGE_UTF8,
    }
    for check, tag in simple.items():
        if check(t):
            return tag, b.empty_table(), b.offsets([])
    if pa.types.is_list(t) or pa.types.is_large_list(t):
        child = _field(b, t.value_field)
        return (_LIST if pa.types.is_list(t) else _LARGE_LIST), b.empty_table(), b.offsets([child])
    if pa.types.is_fixed_size_list(t):
        child = _field(b, t.value_field)
        return _FIXED_LIST, _scalar_table(b, [(4, "<i", t.list_size, 0)]), b.offsets([child])
    if pa.types.is_map(t):
        child = _field(b, pa.field("entries", pa.struct([t.key_field, t.item_field]), nullable=False))
        return _MAP, _scalar_table(b, [(4, "<B", int(t.keys_sorted), 0)]), b.offsets([child])
    if pa.types.is_struct(t):
        members = [_field(b, t.field(i)) for i in range(t.num_fields)]
        return _STRUCT, b.empty_table(), b.offsets(members)
    if pa.types.is_union(t):
        members = [_field(b, t.field(i)) for i in range(t.num_fields)]
        type_ids = b.int32s(list(t.type_codes))
        tail = b.start()
        b.slot(4, "<h", 1 if t.mode == "dense" else 0, 0)
        b.slot_offset(6, type_ids)
        return _UNION, b.end(tail), b.offsets(members)
    raise Unsupported(str(t))


def rust_schema_message(schema: pa.Schema) -> bytes | None:
    """The IPC schema message Rerun's Rust writer makes of `schema` (None: a type not covered)."""
    b = _Builder()
    try:
        fields = [_field(b, f) for f in schema]
    except Unsupported:
        return None
    vector = b.offsets(fields)
    metadata = _metadata(b, schema.metadata) if schema.metadata else None
    tail = b.start()
    b.slot_offset(6, vector)
    if metadata is not None:
        b.slot_offset(8, metadata)
    header = b.end(tail)
    tail = b.start()
    b.slot(4, "<h", _METADATA_V5, 0)
    b.slot(6, "<B", _MESSAGE_HEADER_SCHEMA, 0)
    b.slot_offset(8, header)
    flatbuffer = b.finish(b.end(tail))
    padded = (len(flatbuffer) + 8 + _ALIGNMENT - 1) // _ALIGNMENT * _ALIGNMENT
    return _CONTINUATION + struct.pack("<i", padded - 8) + flatbuffer + bytes(padded - 8 - len(flatbuffer))


def sorbet_schema_sha256(schema: pa.Schema) -> bytes:
    """Rerun's hash of a Sorbet schema: its fields sorted by name, without schema metadata."""
    ordered = pa.schema(sorted(schema, key=lambda f: f.name))
    message = rust_schema_message(ordered)
    if message is None:  # not laid out here: pyarrow's encoding, a stable hash all the same
        message = ordered.serialize().to_pybytes()
    return hashlib.sha256(message).digest()
