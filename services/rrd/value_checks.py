"""What full Arrow validation checks of a chunk's values, read straight from its IPC record batch.

Every chunk a client sends is fully validated before it is accepted (a chunk Rerun would refuse
is refused, and nothing later reads out of bounds), but a pyarrow read and `validate(full=True)`
costs 15-20 us, about as much as filing a one-row chunk. A stream's chunks of one entity share a
record batch header (row count, null counts, buffer offsets and sizes), so everything full
validation checks that the header alone decides is decided once per header (`value_checks`, kept
in the header's `BatchPlan`), and only what lies in the body is checked per chunk
(`values_valid`): each variable-size array's offsets (from a non-negative start, never
decreasing, within the child or the data buffer) and each string array's bytes (UTF-8, each value
starting on a character boundary).

Which arrays, nodes and buffers a type takes follows the IPC format (children after their parent,
pre-order, as `layout._counts` counts them); types not walked here (unions, dictionaries, views)
are left to pyarrow. This check never accepts what pyarrow's full validation refuses
(tests/services/rrd/test_value_checks.py holds them side by side); when it refuses, the caller
asks pyarrow, whose answer stands.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

_TWO_I32 = struct.Struct("<ii")
_TWO_I64 = struct.Struct("<qq")


@dataclass(frozen=True, slots=True)
class OffsetsCheck:
    """One variable-size array's offsets, checked in each chunk."""

    at: int  # where its offsets start, from the start of the record batch message
    count: int  # how many offsets: the array's length + 1
    wide: bool  # 64-bit offsets (large_list, large_binary, large_string)
    limit: int  # the last offset may not pass this: the child array's length, or the data buffer's size
    text_at: int = -1  # a string array's bytes (-1: not a string array)


class _Inconsistent(Exception):
    """The header says something full validation refuses: pyarrow is asked for the verdict."""


class _Walk:
    """Nodes and buffers of a record batch header, taken in IPC order."""

    def __init__(self, nodes: tuple[int, ...], buffers: tuple[int, ...], body: int) -> None:
        self.nodes, self.buffers, self.body = nodes, buffers, body
        self.node = self.buffer = 0
        self.checks: list[OffsetsCheck] = []

    def take_node(self) -> tuple[int, int]:
        length, nulls = self.nodes[2 * self.node], self.nodes[2 * self.node + 1]
        self.node += 1
        if length < 0 or not 0 <= nulls <= length:
            raise _Inconsistent
        return length, nulls

    def take_buffer(self) -> tuple[int, int]:
        """(position from the record batch message's start, size) of the next buffer."""
        offset, size = self.buffers[2 * self.buffer], self.buffers[2 * self.buffer + 1]
        self.buffer += 1
        return self.body + offset, size

    def array(self, t: pa.DataType, minimum: int) -> int:
        """Check an array of type `t` that must hold at least `minimum` values; its length."""
        length, nulls = self.take_node()
        if length < minimum:
            raise _Inconsistent
        if pa.types.is_null(t):
            return length
        _, validity = self.take_buffer()
        if nulls and validity < (length + 7) // 8:
            raise _Inconsistent
        if pa.types.is_boolean(t):
            self._sized(self.take_buffer()[1], (length + 7) // 8)
        elif _fixed_width(t):
            self._sized(self.take_buffer()[1], length * t.bit_width // 8)
        elif _is_binary(t):
            self._binary(t, length)
        elif pa.types.is_list(t) or pa.types.is_large_list(t) or pa.types.is_map(t):
            self._list(t, length)
        elif pa.types.is_fixed_size_list(t):
            self.array(t.value_type, length * t.list_size)
        elif pa.types.is_struct(t):
            for i in range(t.num_fields):
                self.array(t.field(i).type, length)
        else:
            raise _Inconsistent  # not walked here (and not counted by the layout)
        return length

    @staticmethod
    def _sized(size: int, needed: int) -> None:
        if size < needed:
            raise _Inconsistent

    def _offsets(self, length: int, wide: bool) -> tuple[int, int]:
        at, size = self.take_buffer()
        if length:
            self._sized(size, (8 if wide else 4) * (length + 1))
        return at, size

    def _binary(self, t: pa.DataType, length: int) -> None:
        wide = pa.types.is_large_binary(t) or pa.types.is_large_string(t)
        at, _ = self._offsets(length, wide)
        data_at, data_size = self.take_buffer()
        if length:
            text = pa.types.is_string(t) or pa.types.is_large_string(t)
            self.checks.append(OffsetsCheck(at, length + 1, wide, data_size, data_at if text else -1))

    def _list(self, t: pa.DataType, length: int) -> None:
        wide = pa.types.is_large_list(t)
        at, _ = self._offsets(length, wide)
        check = len(self.checks)
        if pa.types.is_map(t):
            # A map's child is a struct of keys and items; full validation refuses null keys.
            values, _ = self.take_node()
            self.take_buffer()  # the entries' validity
            keys_node = self.node
            self.array(t.key_type, values)
            if self.nodes[2 * keys_node + 1]:
                raise _Inconsistent
            self.array(t.item_type, values)
        else:
            values = self.array(t.value_type, 0)
        if length:
            self.checks.insert(check, OffsetsCheck(at, length + 1, wide, values))


def _fixed_width(t: pa.DataType) -> bool:
    return bool(
        pa.types.is_integer(t)
        or pa.types.is_floating(t)
        or pa.types.is_temporal(t)
        or pa.types.is_fixed_size_binary(t)
        or pa.types.is_decimal(t)
    )


def _is_binary(t: pa.DataType) -> bool:
    return bool(
        pa.types.is_string(t) or pa.types.is_binary(t) or pa.types.is_large_string(t) or pa.types.is_large_binary(t)
    )


def value_checks(
    schema: pa.Schema, rows: int, nodes: tuple[int, ...], buffers: tuple[int, ...], body: int
) -> tuple[OffsetsCheck, ...] | None:
    """The per-chunk checks of a record batch with this header (`body`: where its body starts, from
    the record batch message's start); None when the header alone shows a problem or holds a type
    not walked here, so pyarrow must decide."""
    walk = _Walk(nodes, buffers, body)
    try:
        for fld in schema:
            walk.array(fld.type, rows)
    except (_Inconsistent, IndexError):
        return None
    if 2 * walk.node != len(nodes) or 2 * walk.buffer != len(buffers):
        return None
    return tuple(walk.checks)


def values_valid(data: bytes | bytearray | memoryview, pos: int, checks: tuple[OffsetsCheck, ...]) -> bool:
    """Whether the chunk whose record batch message starts at `pos` in `data` passes `checks`.
    False means not known: pyarrow's full validation decides."""
    for check in checks:
        at = pos + check.at
        if check.count == 2:
            first, last = (_TWO_I64 if check.wide else _TWO_I32).unpack_from(data, at)
            if first < 0 or last < first or last > check.limit:
                return False
            if check.text_at >= 0 and not _utf8(data, pos + check.text_at, first, last, None):
                return False
            continue
        offsets = np.frombuffer(data, dtype="<i8" if check.wide else "<i4", count=check.count, offset=at)
        first, last = int(offsets[0]), int(offsets[-1])
        if first < 0 or last > check.limit or bool((offsets[1:] < offsets[:-1]).any()):
            return False
        if check.text_at >= 0 and not _utf8(data, pos + check.text_at, first, last, offsets[1:-1]):
            return False
    return True


def _utf8(data: bytes | bytearray | memoryview, at: int, first: int, last: int, inner: np.ndarray | None) -> bool:
    """Whether the bytes of a string array are UTF-8 and each value starts on a character."""
    if first == last:
        return True
    text = bytes(data[at + first : at + last]) if not isinstance(data, bytes) else data[at + first : at + last]
    try:
        text.decode("utf-8")
    except UnicodeDecodeError:
        return False
    if inner is None or not len(inner):
        return True
    starts = inner[inner < last] - first  # a value that starts at the end is empty
    head = np.frombuffer(text, dtype=np.uint8)[starts]
    return not bool(((head & 0xC0) == 0x80).any())  # no value starts with a continuation byte
