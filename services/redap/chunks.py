"""FetchChunks: a chunk's bytes straight from its hot file or its sealed object by range, never
re-encoded (a snapshot window's chunks: their record batches never re-encoded), found by the chunk
keys clients were given (`keys.py`).

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

Reads are by byte range, neighbouring chunks of a run (closer than `GAP_BYTES`) in one read, up
to `READ_BYTES`; from the warm store several reads are under way at once (`readahead`: its first
byte waits on each). The first response goes as soon as the first read is in, the next ones hold up
to `RESPONSE_BYTES` of chunks (unless one chunk is larger): a call holds at most that and its reads
under way (`readahead.DEPTH` + 1 of `READ_BYTES`) in memory, whatever it asks for. A key is checked
against what it points at (a chunk frame holding that chunk id); a key from before the run was
sealed (or sealed again) is found by its chunk id in the run's index. Which dataset a chunk belongs
to is not part of the call (Rerun's clients send no entry header with it): the read scope is the
authorization."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import pyarrow as pa
from google.protobuf.message import DecodeError

from core.errors import InternalError, InvalidArgumentError, NotFoundError
from services.auth.scopes import Principal
from services.redap.dataframe import read_dataframe_part
from services.redap.depot import Depot
from services.redap.keys import TUID, ChunkLocation, episode_chunk_id, parse_chunk_key
from services.redap.pb import cloud_pb2
from services.redap.recordings import open_recording
from services.rrd import errors as rrd_errors
from services.rrd import limits
from services.rrd.chunk import with_chunk_id
from services.rrd.frames import MESSAGE_HEADER_SIZE, MessageKind, decode_message_header
from services.rrd.protowire import encode_varint, fields
from services.runs.indexed import FIRST_READ_BYTES, GAP_BYTES, IndexedRecording
from services.runs.served import count_served
from services.storage import readahead

READ_BYTES = 8 * 1024 * 1024  # neighbouring chunks are read together up to this
RESPONSE_BYTES = 8 * 1024 * 1024  # chunks per response up to this (a larger chunk goes alone)
_ARROW_CHUNK_ID_FIELD = 6


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
    """One ranged read of a run: neighbouring chunks together."""

    recording: IndexedRecording
    offset: int
    end: int
    chunks: list[ChunkLocation]


def _reads(wanted: list[ChunkLocation], runs: dict[str, IndexedRecording]) -> Iterator[_Read]:
    """Reads in each run's order, chunks closer than `GAP_BYTES` (or overlapping) merged; the bytes
    between them are read and dropped, cheaper than a read's first byte. The first read holds up to
    `FIRST_READ_BYTES` (a larger chunk alone), each next one up to twice the last, up to
    `READ_BYTES`: the first response is out while the client's connection still opens its window
    (a new HTTP/2 stream takes a large first message in many small steps)."""
    by_run: dict[str, list[ChunkLocation]] = {}
    for location in wanted:
        by_run.setdefault(location.run_id, []).append(location)
    limit = min(FIRST_READ_BYTES, READ_BYTES)
    for run_id, locations in by_run.items():
        current: _Read | None = None
        for location in sorted(locations, key=lambda loc: loc.offset):
            if (
                current is not None
                and location.offset - current.end <= GAP_BYTES
                and max(current.end, location.end) - current.offset <= limit
            ):
                current.end = max(current.end, location.end)
                current.chunks.append(location)
                continue
            if current is not None:
                yield current
                limit = min(2 * limit, READ_BYTES)
            current = _Read(runs[run_id], location.offset, location.end, [location])
        if current is not None:
            yield current
            limit = min(2 * limit, READ_BYTES)


def _read(plan: _Read) -> memoryview:
    return memoryview(plan.recording.read(plan.offset, plan.end - plan.offset))


def _responses(wanted: list[ChunkLocation], runs: dict[str, IndexedRecording]) -> Iterator[bytes]:
    pieces: list[bytes | memoryview] = []
    size, first = 0, True  # the first read's chunks go at once: the viewer shows them meanwhile
    depth = max((recording.read_ahead for recording in runs.values()), default=1)
    try:
        for read, data in readahead.read_ahead(_reads(wanted, runs), _read, depth, lambda r: r.end - r.offset):
            count_served("depot", len(read.chunks), read.end - read.offset)
            for location in read.chunks:
                message: bytes | memoryview = _arrow_message(read.recording, location, data, read.offset)
                if location.episode:
                    message = _for_episode(message, location)
                entry = len(message) + 10
                if pieces and size + entry > RESPONSE_BYTES:
                    yield b"".join(pieces)
                    pieces, size = [], 0
                pieces += (b"\x0a" + encode_varint(len(message)), message)  # FetchChunksResponse.chunks (field 1)
                size += entry
            if first and pieces:
                yield b"".join(pieces)
                pieces, size, first = [], 0, False
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
    return TUID.pack(time_ns, inc)
