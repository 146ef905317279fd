"""Damage aimed where Arrow readers trust an IPC stream's data, for the fuzz suites of every
surface that reads a client's Arrow (chunks at ingest, tables in the catalog service's requests)."""

from __future__ import annotations

import itertools
import struct
from collections.abc import Iterator
from dataclasses import dataclass

import pyarrow as pa
from hypothesis import strategies as st

INTERESTING_I32 = [0, 1, -1, 7, 255, 1 << 16, 1 << 30, -(1 << 31), (1 << 31) - 1]
INTERESTING_I64 = [0, -1, 1, 1 << 31, 1 << 40, -(1 << 63), (1 << 63) - 1]


@dataclass
class IpcMap:
    """Where things are in a chunk's Arrow IPC stream: the record batch header (flatbuffer), its
    field nodes (length, null count) and each buffer (validity bitmaps, offsets, values)."""

    header: tuple[int, int]
    nodes: int  # position of the first node's length
    num_nodes: int
    buffers: list[tuple[int, int]]  # (start, length) of the non-empty buffers

    @classmethod
    def of(cls, ipc: bytes) -> IpcMap:
        """The map of an IPC stream of a schema and one record batch, as pyarrow reads it."""
        buffer = pa.py_buffer(ipc)
        reader = pa.BufferReader(buffer)
        schema = pa.ipc.read_schema(pa.ipc.read_message(reader))
        start = reader.tell()
        message = pa.ipc.read_message(reader)
        batch = pa.ipc.read_record_batch(message, schema)
        arrays = [a for column in batch.columns for a in _arrays(column)]
        body = message.body.address - buffer.address
        packed = b"".join(struct.pack("<qq", len(a), a.null_count) for a in arrays)
        nodes = ipc.find(packed, start + 8, body)
        assert nodes > 0, "the field nodes were not found in the record batch header"
        buffers = [
            (b.address - buffer.address, b.size) for a in arrays for b in a.buffers() if b is not None and b.size >= 4
        ]
        return cls((start + 8, body), nodes, len(arrays), buffers)

    def offsets_buffers(self, ipc: bytes) -> list[tuple[int, int]]:
        """(start, entries) of the buffers that look like list or string offsets: int32s from 0,
        never decreasing, at least 3 (so there is a middle one, which a cheap check never reads)."""
        found = []
        for start, length in self.buffers:
            values = struct.unpack_from(f"<{length // 4}i", ipc, start)
            n = len(values)
            while n > 3 and values[n - 1] == 0:  # padding
                n -= 1
            if n >= 3 and values[0] == 0 and all(a <= b for a, b in itertools.pairwise(values[:n])):
                found.append((start, n))
        return found


@st.composite
def damaged(draw: st.DrawFn, ipc: bytes) -> bytes:
    """`ipc` with 1 to 3 edits, aimed where Arrow readers trust the data: an int32 in a buffer (list
    and string offsets) set to a boundary value or moved a little, a bit of a buffer flipped
    (validity bitmaps, values), a field node's length or null count changed, a byte of the record
    batch header flipped (buffer positions, body length), or any byte flipped."""
    data = bytearray(ipc)
    where = IpcMap.of(ipc)
    offsets = where.offsets_buffers(ipc)
    for _ in range(draw(st.integers(1, 3), label="edits")):
        kind = draw(st.sampled_from(["list offset", "offset", "bit", "node", "header", "byte"]), label="kind")
        if kind == "list offset" and offsets:  # a middle offset out of order or past the values
            start, entries = draw(st.sampled_from(offsets), label="offsets buffer")
            pos = start + 4 * draw(st.integers(1, entries - 2), label="entry")
            old = struct.unpack_from("<i", data, pos)[0]
            new = draw(st.sampled_from([old + (1 << 30), old + 1000, -1, -(1 << 31), old + 2]), label="offset")
            data[pos : pos + 4] = struct.pack("<i", max(-(1 << 31), min(new, (1 << 31) - 1)))
        elif kind in ("offset", "bit") and where.buffers:
            if kind == "offset":  # any int32 of any buffer: long offsets buffers are hit most
                slots = [start + 4 * i for start, length in where.buffers for i in range(length // 4)]
                pos = draw(st.sampled_from(slots), label="slot")
                old = struct.unpack_from("<i", data, pos)[0]
                new = draw(
                    st.one_of(
                        st.sampled_from(INTERESTING_I32), st.integers(old - 3, old + 3), st.just(old + (1 << 30))
                    ),
                    label="int32",
                )
                data[pos : pos + 4] = struct.pack("<i", max(-(1 << 31), min(new, (1 << 31) - 1)))
            else:
                start, length = draw(st.sampled_from(where.buffers), label="buffer")
                pos = draw(st.integers(start, start + length - 1), label="position")
                data[pos] ^= 1 << draw(st.integers(0, 7), label="bit")
        elif kind == "node" and where.num_nodes:
            pos = where.nodes + 8 * draw(st.integers(0, 2 * where.num_nodes - 1), label="node field")
            data[pos : pos + 8] = struct.pack("<q", draw(st.sampled_from([*INTERESTING_I64, 2, 3, 5]), label="int64"))
        elif kind == "header":
            pos = draw(st.integers(where.header[0], where.header[1] - 1), label="position")
            data[pos] ^= draw(st.integers(1, 255), label="xor")
        else:
            pos = draw(st.integers(0, len(data) - 1), label="position")
            data[pos] ^= draw(st.integers(1, 255), label="xor")
    return bytes(data)


def fully_valid(ipc: bytes) -> bool:
    """Whether full Arrow validation (what Rerun's reader does) accepts the stream: what a surface
    that files damaged IPC must hold to."""
    try:
        pa.ipc.open_stream(ipc).read_all().validate(full=True)
    except (pa.ArrowException, ValueError):
        return False
    return True


def _arrays(array: pa.Array) -> Iterator[pa.Array]:
    """An array and its descendants in IPC order: one field node each."""
    yield array
    kind = array.type
    if pa.types.is_list(kind) or pa.types.is_large_list(kind) or pa.types.is_fixed_size_list(kind):
        yield from _arrays(array.values)
    elif pa.types.is_struct(kind):
        for i in range(kind.num_fields):
            yield from _arrays(array.field(i))
