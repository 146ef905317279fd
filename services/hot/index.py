"""The chunk index of a hot run: `hot/<run>/chunks.idx`, beside its `run.rrd`.

One record per message of the run file, appended right after the message, in the file's order:
for a chunk, what a sealed run's `chunks.parquet` row holds (`services.rrd.chunk_index.IndexRow`:
id, entity, static, rows, per-timeline min/max, components and their ranges, frame offset and
length) plus what a footer manifest needs besides (the payload's uncompressed size and the chunk's
Arrow schema, written once per distinct schema); for a store info or blueprint activation, its
place. So a live or closed run is indexed as it is written, never by decompressing its chunks again.

The file is a cache of what the run file says, not a second source of truth: it is never fsynced,
a record is checked (CRC-32) when read, and it must describe the run file's frames one after the
other. Readers take its records up to the size of the run file they were given and read what it
lacks (the few messages appended since, or everything if it is missing or damaged) from the run
file itself. After a restart, `recover` keeps the records that match the frames the run file still
holds (its torn tail trimmed), cuts the rest, and indexes the frames it lacks.

Record: u32 payload length, u32 CRC-32 of the payload, then the payload, one of
  L  u32 layout id, the chunk schema (Arrow IPC)
  M  u8 message kind, u8 store kind, i64 offset, i64 length
  C  u8 store kind, u32 layout id, i64 offset, i64 length, i64 rows, i64 uncompressed size,
     16 B chunk id, u16 timelines; per timeline u16 position in the layout, i64 min, i64 max;
     per data column of the layout u8 0 (non-null in every row: the chunk's rows and ranges) or
     1, i64 rows, u16 ranges, per range u16 timeline position, i64 min, i64 max
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import zlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa

from services.rrd import errors as rrd_errors
from services.rrd.chunk import ChunkMeta, ComponentMeta, TimelineMeta, TimeRange, chunk_meta
from services.rrd.chunk_index import BLUEPRINT_ACTIVATION, CHUNK, STORE_INFO, IndexRow, chunk_row, store_kind_name
from services.rrd.decoder import decode_message
from services.rrd.frames import MESSAGE_HEADER_SIZE, STREAM_HEADER_SIZE, MessageKind, decode_message_header
from services.rrd.layout import ChunkLayout, build_layout
from services.rrd.messages import ArrowMessage, Event, StoreInfoMessage, StoreKind, StreamStart

log = logging.getLogger(__name__)

INDEX_FILE = "chunks.idx"
MAGIC = b"FLTHIDX1"
_RECORD = struct.Struct("<II")
_LAYOUT = struct.Struct("<cI")
_MESSAGE = struct.Struct("<cBBqq")
_CHUNK = struct.Struct("<cBIqqqq16sH")
_RANGE = struct.Struct("<Hqq")
_EXPLICIT = struct.Struct("<BqH")
_SAME = b"\0"
_KINDS = {MessageKind.SET_STORE_INFO: STORE_INFO, MessageKind.BLUEPRINT_ACTIVATION: BLUEPRINT_ACTIVATION}
_STORE_KINDS = {int(kind): store_kind_name(kind) for kind in StoreKind}
_READ_BYTES = 1 << 20


class HotEntry:
    """One message of a hot run file: where it is, what it is and, for a chunk, its metadata (what a
    footer manifest is built from). Its index row is made when first asked for (a manifest does not
    need it)."""

    __slots__ = ("_row", "kind", "length", "meta", "offset", "store_kind")

    def __init__(self, kind: str, store_kind: str, offset: int, length: int, meta: ChunkMeta | None = None) -> None:
        self.kind = kind  # chunk | store_info | blueprint_activation, as index rows say
        self.store_kind = store_kind  # recording | blueprint
        self.offset = offset  # of the message's frame
        self.length = length  # of the whole frame
        self.meta = meta
        self._row: IndexRow | None = None

    @property
    def row(self) -> IndexRow:
        if self._row is None:
            if self.meta is not None:
                self._row = chunk_row(self.store_kind, self.offset, self.length, self.meta)
            else:
                self._row = IndexRow(self.kind, self.store_kind, self.offset, self.length)
        return self._row

    @property
    def end(self) -> int:
        return self.offset + self.length


@dataclass(frozen=True)
class HotChunkIndex:
    """Every message of a hot run file up to `size`, in file order."""

    entries: list[HotEntry]
    size: int
    from_index: int  # how many entries came from the index file (the rest were read from the run file)

    @property
    def rows(self) -> list[IndexRow]:
        return [entry.row for entry in self.entries]


def _frame(payload: bytes) -> bytes:
    return _RECORD.pack(len(payload), zlib.crc32(payload)) + payload


class _KnownLayout:
    """A layout written to an index file: its id there, its timelines' positions, and the struct of
    its common chunk record (every timeline, every component `_SAME`)."""

    __slots__ = ("id", "layout", "plain", "positions")

    def __init__(self, layout: ChunkLayout, layout_id: int) -> None:
        self.layout = layout  # kept alive, so its identity (the key) is never reused
        self.id = layout_id
        self.positions = {ix.name: i for i, ix in enumerate(layout.indexes)}
        count = len(layout.indexes)
        self.plain = struct.Struct(_CHUNK.format + _RANGE.format[1:] * count + f"{len(layout.data)}x")


# --- writing ------------------------------------------------------------------------------------


class HotIndexWriter:
    """Appends the records of one run's messages as the run file grows (ingest's thread only).

    A record that cannot be written (disk full) or a message that comes without what its record
    needs stops the index where it is: readers then read the rest from the run file, and the next
    recovery rebuilds it."""

    def __init__(self, path: Path, fd: int, covered: int, length: int, next_layout: int = 0) -> None:
        self.path = path
        self._fd = fd
        self._length = length  # of the index file
        self.covered = covered  # bytes of the run file the records describe
        self.stopped = False
        self._next_layout = next_layout
        # Layouts written to this file, by the identity of the (cached, shared) layout object.
        self._layouts: dict[int, _KnownLayout] = {}

    @classmethod
    def create(cls, directory: Path, covered: int = STREAM_HEADER_SIZE) -> HotIndexWriter:
        path = directory / INDEX_FILE
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o644)
        os.write(fd, MAGIC)
        return cls(path, fd, covered, len(MAGIC))

    def add(self, kind: int, store_kind: StoreKind, offset: int, length: int, meta: ChunkMeta | None) -> None:
        """Index the message just appended to the run file at `offset` (`length`: its whole frame)."""
        if self.stopped:
            return
        try:
            self._add(kind, store_kind, offset, length, meta)
        except Exception as exc:  # the index must never fail a write the run file took
            log.exception("chunk index of hot run %s failed", self.path.parent.name)
            self.stop(f"indexing failed ({exc})")

    def _add(self, kind: int, store_kind: StoreKind, offset: int, length: int, meta: ChunkMeta | None) -> None:
        if offset != self.covered:
            self.stop(f"a message at byte {offset} follows the indexed bytes' end {self.covered}")
        elif kind == MessageKind.ARROW_MSG:
            if meta is None:
                self.stop(f"the chunk at byte {offset} came without its metadata")
            else:
                self._write(self._chunk_records(store_kind, offset, length, meta), offset + length)
        else:
            self._write([_frame(_MESSAGE.pack(b"M", kind, store_kind, offset, length))], offset + length)

    def _chunk_records(self, store_kind: StoreKind, offset: int, length: int, meta: ChunkMeta) -> list[bytes]:
        records = []
        layout = meta.layout
        known = self._layouts.get(id(layout))
        if known is None:
            known = _KnownLayout(layout, self._next_layout)
            self._next_layout += 1
            self._layouts[id(layout)] = known
            records.append(_frame(_LAYOUT.pack(b"L", known.id) + layout.schema.serialize().to_pybytes()))
        rows = meta.num_rows
        timelines = meta.timelines
        if meta.uniform and len(timelines) == len(layout.indexes):
            # The common record: every timeline, every component non-null in every row. One pack.
            values: list[object] = [b"C", store_kind, known.id, offset, length, rows, meta.uncompressed_size]
            values += [meta.chunk_id, len(timelines)]
            for i, t in enumerate(timelines):
                values += [i, t.range.min, t.range.max]
            records.append(_frame(known.plain.pack(*values)))
            return records
        positions = known.positions
        parts = [
            _CHUNK.pack(
                b"C", store_kind, known.id, offset, length, rows, meta.uncompressed_size, meta.chunk_id, len(timelines)
            )
        ]
        parts += [_RANGE.pack(positions[t.name], t.range.min, t.range.max) for t in timelines]
        full = {t.name: t.range for t in timelines}
        for component in meta.components:
            if component.num_rows == rows and component.ranges == full:
                parts.append(_SAME)
                continue
            parts.append(_EXPLICIT.pack(1, component.num_rows, len(component.ranges)))
            parts += [_RANGE.pack(positions[name], r.min, r.max) for name, r in component.ranges.items()]
        records.append(_frame(b"".join(parts)))
        return records

    def _write(self, records: list[bytes], covered: int) -> None:
        data = b"".join(records)
        try:
            written = os.write(self._fd, data)
            if written != len(data):
                raise OSError(f"short write: {written} of {len(data)} bytes")
        except OSError as exc:
            with contextlib.suppress(OSError):  # no half record left behind (readers stop at it anyway)
                os.ftruncate(self._fd, self._length)
            self.stop(f"cannot write it ({exc})")
            return
        self._length += len(data)
        self.covered = covered

    def stop(self, why: str) -> None:
        if not self.stopped:
            self.stopped = True
            log.warning(
                "chunk index of hot run %s stops at byte %d: %s; readers read the rest from the run file "
                "and the next restart rebuilds it",
                self.path.parent.name,
                self.covered,
                why,
            )

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    # --- recovery ---------------------------------------------------------------------------

    @classmethod
    def recover(cls, directory: Path, events: Iterable[Event]) -> HotIndexWriter:
        """The index of a run file reopened after a restart (`events`: every whole message it still
        holds, read as they come, none kept): the records that match those messages are kept, the
        rest cut, and the messages they lack indexed again."""
        path = directory / INDEX_FILE
        matcher = _RecordMatcher(path)
        start: int | None = None
        lacking: list[_Unindexed] = []
        for event in events:
            if isinstance(event, StreamStart):
                continue
            if start is None:
                start = event.offset
            if matcher.matches(event):  # False for good after the first message the index lacks
                continue
            if lacking and lacking[-1].unreadable:
                continue  # the index stops at an unreadable chunk: what follows is read from the file
            lacking.append(_Unindexed.of(event))
        start = STREAM_HEADER_SIZE if start is None else start
        if matcher.cut_at is None:
            writer = cls.create(directory, start)
        else:
            fd = os.open(path, os.O_WRONLY | os.O_APPEND)
            os.ftruncate(fd, matcher.cut_at)
            writer = cls(path, fd, matcher.covered or start, matcher.cut_at, matcher.next_layout)
        if lacking:
            log.info("hot run %s: indexing %d messages its chunk index lacks", directory.name, len(lacking))
            writer._index_lacking(lacking)
        return writer

    def _index_lacking(self, lacking: Sequence[_Unindexed]) -> None:
        for item in lacking:
            if item.unreadable:
                self.stop(item.unreadable)
                return
            self.add(item.kind, item.store_kind, item.offset, item.length, item.meta)


@dataclass(frozen=True)
class _Unindexed:
    """A message of a recovered run file that its index lacks: what indexing it takes, without its
    bytes (a recovered run is read once, as it streams by)."""

    kind: int
    store_kind: StoreKind
    offset: int
    length: int
    meta: ChunkMeta | None
    unreadable: str = ""  # why its chunk cannot be indexed

    @classmethod
    def of(cls, event: Event) -> _Unindexed:
        kind, store_kind, length = (
            int(getattr(event, "kind", MessageKind.END)),
            _store_kind(event),
            _frame_length(event),
        )
        if not isinstance(event, ArrowMessage):
            return cls(kind, store_kind, event.offset, length, None)
        try:
            return cls(kind, store_kind, event.offset, length, chunk_meta(event))
        except rrd_errors.RrdError as exc:
            return cls(
                kind, store_kind, event.offset, length, None, f"its chunk at byte {event.offset} is unreadable ({exc})"
            )


class _RecordMatcher:
    """Walks an index file's records beside the run file's messages, in step, while they match."""

    def __init__(self, path: Path) -> None:
        try:
            data = path.read_bytes()
        except OSError:
            data = b""
        self.cut_at: int | None = None  # where the file is cut after the matching records (None: start anew)
        self.covered = 0  # the end of the last message matched
        self.next_layout = 0
        self._records: Iterator[tuple[int, bytes]] | None = None
        if data.startswith(MAGIC):
            self.cut_at = len(MAGIC)
            self._records = index_records(data)

    def matches(self, event: Event) -> bool:
        """Whether the next record describes `event`; once one does not, none is looked at again."""
        if self._records is None:
            return False
        for end, payload in self._records:
            if payload[:1] == b"L":
                if len(payload) < _LAYOUT.size:
                    break
                self.next_layout = max(self.next_layout, _LAYOUT.unpack_from(payload)[1] + 1)
                continue
            if not _describes(payload, event):
                break
            self.cut_at, self.covered = end, event.offset + _frame_length(event)
            return True
        self._records = None
        return False


def _frame_length(event: Event) -> int:
    return MESSAGE_HEADER_SIZE + len(getattr(event, "raw", b""))


def _store_kind(event: Event) -> StoreKind:
    if isinstance(event, StoreInfoMessage | ArrowMessage):
        return event.store_id.kind
    return StoreKind.BLUEPRINT


def _describes(payload: bytes, event: Event) -> bool:
    """Whether a message or chunk record is that of `event` (same place, same kind, same chunk)."""
    try:
        if payload[:1] == b"M":
            _, kind, _, offset, length = _MESSAGE.unpack_from(payload)
            same_kind = kind == getattr(event, "kind", None)
            return bool(same_kind and offset == event.offset and length == _frame_length(event))
        if payload[:1] == b"C" and isinstance(event, ArrowMessage):
            _, _, _, offset, length, _, _, chunk_id, _ = _CHUNK.unpack_from(payload)
            same_chunk = event.chunk_id is None or chunk_id == event.chunk_id
            return bool(offset == event.offset and length == _frame_length(event) and same_chunk)
    except struct.error:
        return False
    return False


def index_records(data: bytes | memoryview) -> Iterator[tuple[int, bytes]]:
    """(end position, payload) of each whole, intact record after the magic; stops at the first
    record that is cut short or fails its CRC."""
    pos = len(MAGIC)
    while pos + _RECORD.size <= len(data):
        length, crc = _RECORD.unpack_from(data, pos)
        start = pos + _RECORD.size
        end = start + length
        if end > len(data):
            return
        payload = bytes(data[start:end])
        if zlib.crc32(payload) != crc or not payload:
            return
        yield end, payload
        pos = end


# --- reading ------------------------------------------------------------------------------------


def read_hot_index(run_file: Path, size: int) -> HotChunkIndex:
    """The entries of the first `size` bytes of a run file: from its index, and from the run file
    for what the index does not hold (yet)."""
    entries = list(_indexed_entries(run_file.with_name(INDEX_FILE), size))
    from_index = len(entries)
    covered = entries[-1].end if entries else STREAM_HEADER_SIZE
    if covered < size:
        entries += scan_run_file(run_file, covered, size)
    return HotChunkIndex(entries, size, from_index)


def iter_hot_index(run_file: Path, size: int) -> Iterator[HotEntry]:
    """The entries of `read_hot_index`, one at a time as the index is parsed: a reader that goes
    through a run in file order starts on its first messages before the last record is read."""
    covered = STREAM_HEADER_SIZE
    for entry in _indexed_entries(run_file.with_name(INDEX_FILE), size):
        covered = entry.end
        yield entry
    if covered < size:
        yield from scan_run_file(run_file, covered, size)


def _indexed_entries(path: Path, size: int) -> Iterator[HotEntry]:
    """The entries the index file holds, from the run file's first message on, up to `size`."""
    try:
        data = path.read_bytes()
    except OSError:
        return
    if not data.startswith(MAGIC):
        return
    covered = STREAM_HEADER_SIZE
    layouts: dict[int, tuple[ChunkLayout, list[str]]] = {}
    for _, payload in index_records(data):
        try:
            entry = parse_record(payload, layouts)
        except (struct.error, IndexError, KeyError, ValueError, pa.ArrowException, rrd_errors.RrdError) as exc:
            log.warning("chunk index %s is damaged (%s): the rest is read from the run file", path, exc)
            return
        if entry is None:
            continue
        if entry.offset != covered or entry.end > size:
            return  # past what the reader was given, or not the next frame: the rest comes from the run file
        yield entry
        covered = entry.end


def parse_record(payload: bytes, layouts: dict[int, tuple[ChunkLayout, list[str]]]) -> HotEntry | None:
    kind = payload[:1]
    if kind == b"L":
        _, layout_id = _LAYOUT.unpack_from(payload)
        schema = pa.ipc.read_schema(pa.py_buffer(payload[_LAYOUT.size :]))
        layout = build_layout(schema, 0)
        layouts[layout_id] = (layout, [ix.name for ix in layout.indexes])
        return None
    if kind == b"M":
        _, message_kind, store_kind, offset, length = _MESSAGE.unpack_from(payload)
        return HotEntry(_KINDS[message_kind], _STORE_KINDS[store_kind], offset, length)
    if kind != b"C":
        raise ValueError(f"unknown record type {kind!r}")
    _, store_kind, layout_id, offset, length, rows, uncompressed, chunk_id, count = _CHUNK.unpack_from(payload)
    layout, names = layouts[layout_id]
    pos = _CHUNK.size
    ranges: dict[str, TimeRange] = {}
    for _ in range(count):
        position, lo, hi = _RANGE.unpack_from(payload, pos)
        pos += _RANGE.size
        ranges[names[position]] = TimeRange(lo, hi)
    timelines = tuple(
        TimelineMeta(ix.name, ix.type, ranges[ix.name], ix.is_sorted, ix.field)
        for ix in layout.indexes
        if ix.name in ranges
    )
    components = []
    for column in layout.data:
        if payload[pos] == 0:
            pos += 1
            num_rows, column_ranges = rows, ranges
        else:
            _, num_rows, n = _EXPLICIT.unpack_from(payload, pos)
            pos += _EXPLICIT.size
            column_ranges = {}
            for _ in range(n):
                position, lo, hi = _RANGE.unpack_from(payload, pos)
                pos += _RANGE.size
                column_ranges[names[position]] = TimeRange(lo, hi)
        components.append(
            ComponentMeta(
                column.column,
                column.component,
                column.archetype,
                column.component_type,
                num_rows,
                column_ranges,
                column.field,
            )
        )
    meta = ChunkMeta(
        chunk_id,
        layout.entity_path,
        not layout.indexes,
        rows,
        timelines,
        tuple(components),
        length - MESSAGE_HEADER_SIZE,
        uncompressed,
        layout.row_id_field,
        layout,
    )
    return HotEntry(CHUNK, _STORE_KINDS[store_kind], offset, length, meta)


def scan_run_file(run_file: Path, start: int, size: int) -> list[HotEntry]:
    """Entries of the whole messages between `start` and `size` of a run file, read from it."""
    entries: list[HotEntry] = []
    try:
        fh = open(run_file, "rb")  # noqa: SIM115 - closed below; a missing file is an empty answer
    except OSError:
        return entries
    with fh:
        fh.seek(start)
        offset = start
        while offset + MESSAGE_HEADER_SIZE <= size:
            head = fh.read(MESSAGE_HEADER_SIZE)
            if len(head) < MESSAGE_HEADER_SIZE:
                break
            kind, length = decode_message_header(head)
            end = offset + MESSAGE_HEADER_SIZE + length
            if end > size:
                break
            raw = fh.read(length)
            if len(raw) < length:
                break
            entries.append(_scanned_entry(decode_message(kind, raw, offset), offset, end - offset))
            offset = end
    return entries


def _scanned_entry(message: object, offset: int, length: int) -> HotEntry:
    if isinstance(message, ArrowMessage):
        meta = chunk_meta(message)
        return HotEntry(CHUNK, store_kind_name(message.store_id.kind), offset, length, meta)
    if isinstance(message, StoreInfoMessage):
        return HotEntry(STORE_INFO, store_kind_name(message.store_id.kind), offset, length)
    return HotEntry(BLUEPRINT_ACTIVATION, "blueprint", offset, length)
