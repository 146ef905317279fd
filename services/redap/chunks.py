"""Chunk keys and FetchChunks: a chunk's bytes straight from its hot file or its sealed object by
range, never re-encoded (a snapshot window's chunks: their record batches never re-encoded).

A chunk key is Rerun's `ChunkKey` message, which clients treat as opaque and hand back to
FetchChunks: the chunk's id and an `RrdChunkLocation` whose `url` is `fleet:SEGMENT` and whose
offset and length are those of the chunk's whole frame in the run's recording (its 16-byte
message header included, as Rerun's direct-URL readers expect). SEGMENT is the run id, or a
snapshot's window episode `RUN~N` (`snapshots.py`), read from run RUN.

FetchChunks answers with the stored `ArrowMsg` bytes exactly: each response is built as the
protobuf encoding of `FetchChunksResponse` (field 1, length-delimited, around each stored message),
served with a raw-bytes serializer.

A snapshot's window episode (`RUN~N`) is the one exception. Rerun's clients file each chunk they
fetch under the segment its message's store id names, and keep one chunk per chunk id over all the
segments a query reads (in Rerun a chunk is one segment's), so a chunk two windows of a run share
(their static chunks, at least) would reach one of them only. Its chunks are therefore served
under ids of its own (`episode_chunk_id`, in its manifest and candidate rows too), its store id
naming it: the Arrow schema's `rerun:id` and the message's fields say so, the record batch is
copied byte for byte, the payload compressed again (`services.rrd.chunk.with_chunk_id`).

Reads are by byte range, adjacent chunks of a run in one read, one read and one response (a few
chunks, at most `RESPONSE_BYTES` unless one chunk is larger) in memory at a time. A key is checked
against what it points at (a chunk frame holding that chunk id); a key from before the run was
sealed (or sealed again) is found by its chunk id in the run's index. Which dataset a chunk belongs
to is not part of the call (Rerun's clients send no entry header with it): the read scope is the
authorization."""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import pyarrow as pa
from google.protobuf.message import DecodeError

from core.errors import InternalError, InvalidArgumentError, NotFoundError
from services.auth.scopes import Principal
from services.redap.dataframe import read_dataframe_part
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.recordings import open_recording
from services.rrd import errors as rrd_errors
from services.rrd import limits
from services.rrd.chunk import with_chunk_id
from services.rrd.frames import MESSAGE_HEADER_SIZE, MessageKind, decode_message_header
from services.rrd.protowire import fields
from services.runs.indexed import IndexedRecording
from services.runs.served import count_served

RUN_URL_PREFIX = "fleet:"
READ_BYTES = 8 * 1024 * 1024  # adjacent chunks are read together up to this
RESPONSE_BYTES = 8 * 1024 * 1024  # chunks per response up to this (a larger chunk goes alone)
_ARROW_CHUNK_ID_FIELD = 6
EPISODE_SEPARATOR = "~"  # a snapshot episode's segment id: RUN~N (snapshots.SEGMENT_SEPARATOR)
_TUID = struct.Struct(">QQ")


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


def _varint(value: int) -> bytes:
    out = bytearray()
    while value > 0x7F:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _delimited(tag: int, payload: bytes) -> bytes:
    return bytes((tag,)) + _varint(len(payload)) + payload


def chunk_key(segment_id: str, offset: int, length: int, chunk_id: bytes) -> bytes:
    """The key FindChunks and GetRrdManifest hand out for a chunk of a segment (a run id, or a
    snapshot episode's `RUN~N`; `chunk_id`: its 16 bytes).

    Written field by field as protobuf serializes `ChunkKey{chunk_id: Tuid, data_source_kind: RRD,
    location: RrdChunkLocation{url, offset, length}}` (the same bytes, checked in the tests), as a
    manifest needs one per chunk and the message classes cost ten times more."""
    time_ns, inc = int.from_bytes(chunk_id[:8], "big"), int.from_bytes(chunk_id[8:16], "big")
    url = f"{RUN_URL_PREFIX}{segment_id}".encode()
    location = _delimited(0x0A, url) + b"\x10" + _varint(offset) + b"\x18" + _varint(length)
    tuid = b"\x09" + time_ns.to_bytes(8, "little") + b"\x11" + inc.to_bytes(8, "little")
    return _delimited(0x0A, tuid) + b"\x10" + _varint(cloud_pb2.DATA_SOURCE_KIND_RRD) + _delimited(0x1A, location)


def episode_chunk_id(segment_id: str, chunk_id: bytes) -> bytes:
    """The id a snapshot episode's candidate row gives a chunk: Rerun's clients keep one candidate
    row per chunk id over all the segments a query reads (in Rerun a chunk is one segment's), so a
    chunk two episodes share would be read for one of them only. The chunk's 8 bytes of time, then
    8 bytes of a digest of the segment and the chunk id; the row's key names the chunk itself."""
    digest = hashlib.sha256(segment_id.encode() + b"\x00" + chunk_id).digest()
    return chunk_id[:8] + digest[:8]


def chunk_keys(
    segment_id: str, payload_offsets: Sequence[int], payload_sizes: Sequence[int], chunk_ids: Sequence[bytes]
) -> list[bytes]:
    """Keys of a manifest's chunks, from its `chunk_byte_offset` and `chunk_byte_size` (those of
    the ArrowMsg payload: the key's frame starts 16 bytes before)."""
    return [
        chunk_key(segment_id, offset - MESSAGE_HEADER_SIZE, size + MESSAGE_HEADER_SIZE, chunk_id)
        for offset, size, chunk_id in zip(payload_offsets, payload_sizes, chunk_ids, strict=True)
    ]


def parse_chunk_key(key: bytes) -> ChunkLocation:
    """Where a chunk key a client sent points; INVALID_ARGUMENT if it is none of ours."""
    try:
        parsed = cloud_pb2.ChunkKey.FromString(key)
        location = cloud_pb2.RrdChunkLocation.FromString(parsed.location)
    except Exception as exc:  # protobuf's DecodeError and friends: the client sent something else
        raise InvalidArgumentError("a chunk_key is not one this depot handed out: ask GetRrdManifest again") from exc
    if not location.url.startswith(RUN_URL_PREFIX) or location.length <= MESSAGE_HEADER_SIZE:
        raise InvalidArgumentError("a chunk_key is not one this depot handed out: ask GetRrdManifest again")
    # Big-endian time then counter, as Rerun's Arrow tables (and our indexes) hold chunk ids.
    chunk_id = _TUID.pack(parsed.chunk_id.time_ns, parsed.chunk_id.inc) if parsed.HasField("chunk_id") else None
    segment = location.url[len(RUN_URL_PREFIX) :]
    run_id, separator, number = segment.partition(EPISODE_SEPARATOR)
    if separator and not (run_id and number.isascii() and number.isdigit()):
        raise InvalidArgumentError("a chunk_key is not one this depot handed out: ask GetRrdManifest again")
    return ChunkLocation(run_id, location.offset, location.length, chunk_id, segment if separator else "")


# --- FetchChunks ---------------------------------------------------------------------------------


def fetch_chunks(depot: Depot, principal: Principal, request: cloud_pb2.FetchChunksRequest) -> Iterator[bytes]:
    """Serialized `FetchChunksResponse`s holding the stored bytes of the requested chunks. Every key
    and every run is checked before the first answer, so a bad request fails whole."""
    wanted = requested_chunks(request)
    runs: dict[str, IndexedRecording] = {}
    try:
        for location in wanted:
            if location.run_id not in runs:
                runs[location.run_id] = open_recording(depot, location.run_id, cached=True)
            recording = runs[location.run_id]
            if location.end > recording.size:
                raise InvalidArgumentError(
                    f"a chunk_key points past the end of run {location.run_id!r} ({location.end} > "
                    f"{recording.size} bytes): ask GetRrdManifest again"
                )
        return _responses(wanted, runs)
    except BaseException:
        for recording in runs.values():
            recording.close()
        raise


def requested_chunks(request: cloud_pb2.FetchChunksRequest) -> list[ChunkLocation]:
    """The chunks a request names (its `chunk_key` column, over all parts), each once."""
    wanted: dict[tuple[str, int, int], ChunkLocation] = {}  # by segment: a chunk is sent once per segment
    for i, part in enumerate(request.chunk_infos):
        with limits.holding(part.uncompressed_size):
            for key in _chunk_keys(read_dataframe_part(part, f"chunk_infos[{i}]")):
                location = parse_chunk_key(key)
                wanted.setdefault((location.episode or location.run_id, location.offset, location.length), location)
    return list(wanted.values())


def _chunk_keys(table: pa.Table) -> list[bytes]:
    if "chunk_key" not in table.column_names:
        raise InvalidArgumentError("FetchChunks needs a chunk_key column, as GetRrdManifest and FindChunks give")
    column = table.column("chunk_key")
    if not (pa.types.is_binary(column.type) or pa.types.is_large_binary(column.type)) or column.null_count:
        raise InvalidArgumentError("a chunk_key is null or not binary: send the keys as they were given")
    keys: list[bytes] = column.to_pylist()
    return keys


@dataclass
class _Read:
    """One ranged read of a run: adjacent chunks together."""

    recording: IndexedRecording
    offset: int
    end: int
    chunks: list[ChunkLocation]


def _reads(wanted: list[ChunkLocation], runs: dict[str, IndexedRecording]) -> Iterator[_Read]:
    """Reads in each run's order, adjacent (or overlapping) chunks merged up to `READ_BYTES`."""
    by_run: dict[str, list[ChunkLocation]] = {}
    for location in wanted:
        by_run.setdefault(location.run_id, []).append(location)
    for run_id, locations in by_run.items():
        current: _Read | None = None
        for location in sorted(locations, key=lambda loc: loc.offset):
            if (
                current is not None
                and location.offset <= current.end
                and max(current.end, location.end) - current.offset <= READ_BYTES
            ):
                current.end = max(current.end, location.end)
                current.chunks.append(location)
                continue
            if current is not None:
                yield current
            current = _Read(runs[run_id], location.offset, location.end, [location])
        if current is not None:
            yield current


def _responses(wanted: list[ChunkLocation], runs: dict[str, IndexedRecording]) -> Iterator[bytes]:
    pieces: list[bytes | memoryview] = []
    size = 0
    try:
        for read in _reads(wanted, runs):
            data = memoryview(read.recording.read(read.offset, read.end - read.offset))
            count_served("depot", len(read.chunks), read.end - read.offset)
            for location in read.chunks:
                message: bytes | memoryview = _arrow_message(read.recording, location, data, read.offset)
                if location.episode:
                    message = _for_episode(message, location)
                entry = len(message) + 10
                if pieces and size + entry > RESPONSE_BYTES:
                    yield b"".join(pieces)
                    pieces, size = [], 0
                pieces += (b"\x0a" + _varint(len(message)), message)  # FetchChunksResponse.chunks (field 1)
                size += entry
        if pieces:
            yield b"".join(pieces)
    finally:
        for recording in runs.values():
            recording.close()


def _arrow_message(recording: IndexedRecording, location: ChunkLocation, data: memoryview, base: int) -> memoryview:
    """The stored ArrowMsg the key points at, checked: a chunk frame of that length holding that
    chunk id. Else the chunk is looked up by id in the run's index (a key handed out before the run
    was sealed, or sealed again); NOT_FOUND if the run does not hold it."""
    start = location.offset - base
    frame = data[start : start + location.length]
    if _is_chunk_frame(frame, location):
        return frame[MESSAGE_HEADER_SIZE:]
    row = recording.chunk_row(location.chunk_id) if location.chunk_id is not None else None
    if row is not None:
        moved = ChunkLocation(location.run_id, row.offset, row.length, location.chunk_id, location.episode)
        frame = memoryview(recording.read(row.offset, row.length))
        if _is_chunk_frame(frame, moved):
            return frame[MESSAGE_HEADER_SIZE:]
    raise NotFoundError(
        f"run {location.run_id!r} holds no chunk where a chunk_key points (byte {location.offset}): "
        "its recording changed since the key was given; ask GetRrdManifest again"
    )


def _for_episode(message: bytes | memoryview, location: ChunkLocation) -> bytes:
    """The stored ArrowMsg as a chunk of the episode it is fetched for: its id the episode's
    (`episode_chunk_id`), its store id naming the episode (`chunks.with_chunk_id`: the record
    batch copied byte for byte)."""
    chunk_id = location.chunk_id or b""
    try:
        return with_chunk_id(bytes(message), episode_chunk_id(location.episode, chunk_id), location.episode)
    except (rrd_errors.RrdError, DecodeError, pa.ArrowInvalid) as exc:
        raise InternalError(
            f"run {location.run_id!r} holds a chunk at byte {location.offset} that cannot be served as a "
            f"snapshot episode's ({exc})"
        ) from exc


def _is_chunk_frame(frame: memoryview, location: ChunkLocation) -> bool:
    if len(frame) != location.length:
        return False
    kind, length = decode_message_header(frame)
    if kind != MessageKind.ARROW_MSG or length != location.length - MESSAGE_HEADER_SIZE:
        return False
    if location.chunk_id is None:
        return True
    try:
        for number, _, start, end in fields(frame[MESSAGE_HEADER_SIZE:]):
            if number == _ARROW_CHUNK_ID_FIELD:
                return _tuid_bytes(frame[MESSAGE_HEADER_SIZE + start : MESSAGE_HEADER_SIZE + end]) == location.chunk_id
    except rrd_errors.RrdError:
        return False
    return True  # an ArrowMsg of an SDK that did not name its chunk in the message: the frame checks suffice


def _tuid_bytes(raw: memoryview) -> bytes | None:
    """The 16 bytes of a serialized `Tuid{fixed64 time_ns = 1; fixed64 inc = 2}`."""
    time_ns = inc = 0
    try:
        for number, _, start, _end in fields(raw):
            if number == 1:
                time_ns = int.from_bytes(raw[start : start + 8], "little")
            elif number == 2:
                inc = int.from_bytes(raw[start : start + 8], "little")
    except rrd_errors.RrdError:
        return None
    return _TUID.pack(time_ns, inc)
