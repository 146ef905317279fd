"""Chunk keys: what GetRrdManifest, FindChunks and QueryDataset hand out for each chunk, and what
FetchChunks is given back.

A chunk key is Rerun's `ChunkKey` message, which clients treat as opaque: the chunk's id and an
`RrdChunkLocation` whose `url` is `fleet:SEGMENT` and whose offset and length are those of the
chunk's whole frame in the run's recording (its 16-byte message header included, as Rerun's
direct-URL readers expect). SEGMENT is the run id, or a snapshot's window episode `RUN~N`
(`snapshots.py`), read from run RUN.

A manifest needs a key per chunk: tens of thousands for a run of 50 GB, which protobuf's message
classes (or a Python loop writing the bytes) took a few hundred milliseconds to make, before the
manifest's first byte. `key_column` writes them all at once with numpy, field by field as protobuf
serializes the message (the same bytes, checked in the tests against protobuf's own)."""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyarrow as pa

from core.errors import InvalidArgumentError
from services.redap.pb import cloud_pb2
from services.rrd.frames import MESSAGE_HEADER_SIZE
from services.rrd.protowire import encode_varint

RUN_URL_PREFIX = "fleet:"
EPISODE_SEPARATOR = "~"  # a snapshot episode's segment id: RUN~N (snapshots.SEGMENT_SEPARATOR)
TUID = struct.Struct(">QQ")  # a chunk id's 16 bytes: time, then counter, big-endian
_VARINT_BYTES = 10  # of a uint64
_NOT_OURS = "a chunk_key is not one this depot handed out: ask GetRrdManifest again"


@dataclass(frozen=True)
class ChunkLocation:
    run_id: str
    offset: int  # of the chunk's frame (its message header) in the run's recording
    length: int  # of the whole frame
    chunk_id: bytes | None = None  # the 16 bytes the key names (None: the key names none)
    episode: str = ""  # the snapshot episode's segment id (RUN~N) it is fetched for; "": the run's

    @property
    def end(self) -> int:
        return self.offset + self.length


def key_column(
    segment_id: str, offsets: Sequence[int] | Any, lengths: Sequence[int] | Any, chunk_ids: pa.Array | Sequence[bytes]
) -> pa.BinaryArray:
    """The keys of a segment's chunks (a run id, or a snapshot episode's `RUN~N`), one per frame
    `offsets[i]`, `lengths[i]` (whole frames) holding chunk `chunk_ids[i]` (16 bytes; shorter or
    None: zeros), as an Arrow column.

    Each key is `ChunkKey{chunk_id: Tuid{time_ns, inc}, data_source_kind: RRD, location:
    RrdChunkLocation{url, offset, length}}` serialized: fields in number order, the Tuid's fixed64s
    little-endian (the chunk id holds them big-endian), every field written (they are optional)."""
    offset_values = np.asarray(offsets, np.uint64).reshape(-1)
    length_values = np.asarray(lengths, np.uint64).reshape(-1)
    count = len(offset_values)
    ids = _id_bytes(chunk_ids, count)
    url = f"{RUN_URL_PREFIX}{segment_id}".encode()
    url_field = b"\x0a" + encode_varint(len(url)) + url
    offset_varint, length_varint = _varints(offset_values), _varints(length_values)
    # RrdChunkLocation: url (1), offset (2), length (3)
    location_length = len(url_field) + 2 + offset_varint[1] + length_varint[1]
    tuid = 2 + 2 * 8  # Tuid: time_ns (1, fixed64), inc (2, fixed64)
    pieces = [
        _constant(b"\x0a" + encode_varint(tuid) + b"\x09", count),  # ChunkKey.chunk_id (1)
        (ids[:, 7::-1], np.full(count, 8)),
        _constant(b"\x11", count),
        (ids[:, 15:7:-1], np.full(count, 8)),
        _constant(b"\x10" + encode_varint(cloud_pb2.DATA_SOURCE_KIND_RRD) + b"\x1a", count),  # (2), then location (3)
        _varints(location_length),
        _constant(url_field + b"\x10", count),
        offset_varint,
        _constant(b"\x18", count),
        length_varint,
    ]
    return _rows_of(pieces, count)


def chunk_key(segment_id: str, offset: int, length: int, chunk_id: bytes) -> bytes:
    """One chunk's key (`key_column` for one frame)."""
    key: bytes = key_column(segment_id, [offset], [length], [chunk_id])[0].as_py()
    return key


def episode_chunk_id(segment_id: str, chunk_id: bytes) -> bytes:
    """The id a snapshot episode's candidate row gives a chunk: Rerun's clients keep one candidate
    row per chunk id over all the segments a query reads (in Rerun a chunk is one segment's), so a
    chunk two episodes share would be read for one of them only. The chunk's 8 bytes of time, then
    8 bytes of a digest of the segment and the chunk id; the row's key names the chunk itself."""
    digest = hashlib.sha256(segment_id.encode() + b"\x00" + chunk_id).digest()
    return chunk_id[:8] + digest[:8]


def parse_chunk_key(key: bytes) -> ChunkLocation:
    """Where a chunk key a client sent points; INVALID_ARGUMENT if it is none of ours."""
    try:
        parsed = cloud_pb2.ChunkKey.FromString(key)
        location = cloud_pb2.RrdChunkLocation.FromString(parsed.location)
    except Exception as exc:  # protobuf's DecodeError and friends: the client sent something else
        raise InvalidArgumentError(_NOT_OURS) from exc
    if not location.url.startswith(RUN_URL_PREFIX) or location.length <= MESSAGE_HEADER_SIZE:
        raise InvalidArgumentError(_NOT_OURS)
    # Big-endian time then counter, as Rerun's Arrow tables (and our indexes) hold chunk ids.
    chunk_id = TUID.pack(parsed.chunk_id.time_ns, parsed.chunk_id.inc) if parsed.HasField("chunk_id") else None
    segment = location.url[len(RUN_URL_PREFIX) :]
    run_id, separator, number = segment.partition(EPISODE_SEPARATOR)
    if separator and not (run_id and number.isascii() and number.isdigit()):
        raise InvalidArgumentError(_NOT_OURS)
    return ChunkLocation(run_id, location.offset, location.length, chunk_id, segment if separator else "")


# --- writing many keys at once --------------------------------------------------------------------

Piece = tuple[Any, Any]  # (bytes of each row: uint8 matrix, how many of them each row uses)


def _varints(values: Any) -> Piece:
    """Each value's protobuf varint: seven bits a byte, low first, the high bit set on all but the last."""
    values = np.asarray(values, np.uint64)
    shifts = np.arange(_VARINT_BYTES, dtype=np.uint64) * np.uint64(7)
    groups = ((values[:, None] >> shifts) & np.uint64(0x7F)).astype(np.uint8)
    used = 1 + ((values[:, None] >> shifts[1:]) > 0).sum(axis=1)
    groups[np.arange(_VARINT_BYTES) < (used[:, None] - 1)] |= 0x80
    return groups[:, : int(used.max(initial=1))], used


def _constant(data: bytes, count: int) -> Piece:
    row = np.frombuffer(data, np.uint8)
    return np.broadcast_to(row, (count, len(row))), np.full(count, len(row))


def _id_bytes(chunk_ids: pa.Array | Sequence[bytes], count: int) -> Any:
    """The chunk ids as a (count, 16) uint8 matrix."""
    if isinstance(chunk_ids, pa.ChunkedArray):
        chunk_ids = chunk_ids.combine_chunks()
    if isinstance(chunk_ids, pa.FixedSizeBinaryArray) and chunk_ids.type.byte_width == 16 and not chunk_ids.null_count:
        data = np.frombuffer(chunk_ids.buffers()[1], np.uint8)
        return data[chunk_ids.offset * 16 : (chunk_ids.offset + count) * 16].reshape(count, 16)
    listed = chunk_ids.to_pylist() if isinstance(chunk_ids, pa.Array) else chunk_ids
    joined = b"".join((chunk_id or b"").rjust(16, b"\x00")[:16] for chunk_id in listed)
    return np.frombuffer(joined, np.uint8).reshape(count, 16)


def _rows_of(pieces: list[Piece], count: int) -> pa.BinaryArray:
    """A binary column whose row i is the first `used[i]` bytes of each piece's row i, in order."""
    matrix = np.concatenate([np.asarray(data, np.uint8) for data, _ in pieces], axis=1)
    kept = np.concatenate([np.arange(data.shape[1]) < np.asarray(used)[:, None] for data, used in pieces], axis=1)
    ends = np.zeros(count + 1, np.int32)
    np.cumsum(kept.sum(axis=1), out=ends[1:])
    body = matrix[kept]  # row-major: each row's bytes, rows in order
    return pa.Array.from_buffers(pa.binary(), count, [None, pa.py_buffer(ends), pa.py_buffer(body)])
