"""Importing the .rrd files robots write with Rerun's FileSink, progressively while they grow.

`FileTail` reads one file from where it stopped and returns the whole messages appended since,
never one whose bytes are not all written yet. `watch.FileWatcher` finds the files under the watched
directories (notified by the file system, and by a periodic rescan where it does not notify) and
hands their new messages to the agent in bounded batches. Where a file stands is a `FileProgress`,
which the agent stores once it has filed the messages before it: a restart resumes there, so
messages may be read twice (chunk ids deduplicate them) but never skipped.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import logging
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import xxhash

from services.rrd import errors, limits
from services.rrd.decoder import DEFAULT_MAX_MESSAGE_SIZE, decode_message
from services.rrd.frames import (
    FOOTER_ENTRY_SIZE,
    FOOTER_FIXED_SIZE,
    FOOTER_MAGIC,
    MESSAGE_HEADER_SIZE,
    STREAM_HEADER_SIZE,
    MessageKind,
    decode_footer_entry,
    decode_message_header,
    decode_stream_header,
    footer_crc,
    looks_like_stream_header,
)
from services.rrd.messages import (
    ArrowMessage,
    BlueprintActivationMessage,
    EndMessage,
    Event,
    Message,
    StreamFooter,
    StreamStart,
)
from services.rrd.store_ids import StoreIdResolver

log = logging.getLogger(__name__)

BATCH_BYTES = 8 * 1024 * 1024  # messages handed over per call: bounds the memory one file takes
DEFAULT_IDLE_S = 60.0  # a file without End is complete once it has not grown for this long
DEFAULT_RESCAN_S = 5.0


class Phase(enum.StrEnum):
    """What the bytes at `FileProgress.offset` are expected to be."""

    STREAM_HEADER = "stream_header"  # the file's start, or what follows a stream's footer
    MESSAGES = "messages"  # a message header (or the header of a stream concatenated without End)
    FOOTER = "footer"  # after End: its stream footer, a new stream, or nothing


@dataclass
class FileProgress:
    """Where the import of one file stands; the agent stores it with the messages it filed."""

    path: str
    inode: int = 0
    offset: int = 0  # the end of the last whole message read: reading resumes here
    size: int = 0  # the file's size and mtime when it was last read
    mtime_ns: int = 0
    complete: bool = False  # End (and footer) read, or idle: read again only if it grows
    phase: Phase = Phase.STREAM_HEADER
    stream_offset: int = 0  # the current stream's header
    stream_index: int = -1  # -1: no stream header read yet
    # After End: its payload's stream-relative offset, length and xxh32, which the footer must match.
    end_start: int = 0
    end_length: int = 0
    end_crc: int = 0
    damaged_at: int | None = None  # reading stopped here at damaged data, until the file is replaced
    damage: str = ""
    # xxh32 of the bytes just before `offset`: a file rewritten in place (same inode) that has grown
    # past `size` since it was last seen differs there from the one that was read.
    mark: int = 0

    @property
    def ended(self) -> bool:
        """The last stream read ended with End (a stream may still follow)."""
        return self.stream_index >= 0 and self.phase is not Phase.MESSAGES

    def to_dict(self) -> dict[str, Any]:
        data = dataclasses.asdict(self)
        data["phase"] = self.phase.value
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> FileProgress:
        """The progress `to_dict` gave; unknown keys are ignored, missing ones take their default."""
        values: dict[str, Any] = {}
        for fld in dataclasses.fields(cls):
            if fld.name not in data:
                if fld.name == "path":
                    raise ValueError("file progress has no 'path': store what FileProgress.to_dict() returns")
                continue
            values[fld.name] = _checked(fld.name, data[fld.name])
        return cls(**values)


_FIELD_TYPES: dict[str, tuple[type, ...]] = {"path": (str,), "complete": (bool,), "damage": (str,), "phase": (str,)}


def _checked(name: str, value: Any) -> Any:
    if name == "damaged_at" and value is None:
        return None
    expected = _FIELD_TYPES.get(name, (int,))
    if not isinstance(value, expected) or (expected == (int,) and isinstance(value, bool)):
        raise ValueError(f"file progress {name!r} is {value!r}, expected {expected[0].__name__}")
    if name == "phase":
        if value not in Phase.__members__.values():
            raise ValueError(f"file progress 'phase' is {value!r}, expected one of {', '.join(Phase)}")
        return Phase(str(value))
    return value


@dataclass
class TailRead:
    """What one `FileTail.read` found."""

    events: list[Event]
    progress: FileProgress  # after these events: store it once they are filed
    more: bool  # stopped at the batch size: read again
    completed: bool  # the file became complete with this read
    started_over: bool  # the file was replaced or truncated: the events start at byte 0 again


class _Stop(enum.Enum):
    WAIT = "wait"  # the next unit is not all written yet
    FULL = "full"  # the next message does not fit in this batch


class FileTail:
    """Reads one growing .rrd file: each `read` returns the whole messages written since the last.

    Events are what `iter_events` yields for the same bytes (stream starts, messages with their
    raw bytes, stream footers), each once. A file replaced (another inode) or rewritten (shorter,
    or other bytes before `offset`) is read again from byte 0. Damaged data stops the tail there
    with one warning. Not thread-safe: one `read` at a time."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        progress: FileProgress | None = None,
        *,
        idle_s: float = DEFAULT_IDLE_S,
        max_message_size: int = DEFAULT_MAX_MESSAGE_SIZE,
        max_chunk_bytes: int | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = Path(path)
        self._p = dataclasses.replace(progress) if progress is not None else FileProgress(str(path))
        self.idle_s = idle_s
        self.max_message_size = max_message_size
        self.max_chunk_bytes = max_chunk_bytes if max_chunk_bytes is not None else limits.max_chunk_bytes()
        self._clock = clock
        self._last_change = clock()
        self._resolver = StoreIdResolver()
        # Resumed mid-stream, the stream's SetStoreInfo lies behind: read back if a store id needs it.
        self._store_ids_known = self._p.offset <= self._p.stream_offset + STREAM_HEADER_SIZE

    @property
    def progress(self) -> FileProgress:
        return dataclasses.replace(self._p)

    def idle_deadline(self) -> float | None:
        """When (on `clock`) the file becomes complete if it does not grow; None if complete."""
        return None if self._p.complete else self._last_change + self.idle_s

    def read(self, max_bytes: int = BATCH_BYTES) -> TailRead:
        """The whole messages appended since the last read, up to about `max_bytes` of them (at
        least one). Raises OSError (FileNotFoundError when the file is gone), and then stays where
        it was."""
        saved = self.progress
        try:
            return self._read(max_bytes)
        except BaseException:
            self._p = saved
            raise

    def _read(self, max_bytes: int) -> TailRead:
        with open(self.path, "rb") as fh:
            st = os.fstat(fh.fileno())
            started_over = self._check_replaced(fh.fileno(), st)
            p = self._p
            if (st.st_size, st.st_mtime_ns) != (p.size, p.mtime_ns):
                self._last_change = self._clock()
            if p.complete and st.st_size <= p.size:
                return TailRead([], self.progress, False, False, started_over)
            p.complete = False
            events: list[Event] = []
            more = False
            if p.damaged_at is None:
                events, more = self._read_events(fh.fileno(), st.st_size, max_bytes)
            p.size, p.mtime_ns, p.mark = st.st_size, st.st_mtime_ns, _mark(fh.fileno(), p.offset)
        idle = self._clock() - self._last_change >= self.idle_s
        p.complete = not more and ((p.ended and p.offset == p.size) or idle)
        return TailRead(events, self.progress, more, p.complete, started_over)

    def _check_replaced(self, fd: int, st: os.stat_result) -> bool:
        p = self._p
        if p.inode == 0:
            p.inode = st.st_ino
            return False
        if st.st_ino == p.inode and st.st_size >= max(p.size, p.offset) and _mark(fd, p.offset) == p.mark:
            return False
        log.info("%s was replaced or truncated: reading it again from byte 0", self.path)
        self._p = FileProgress(str(self.path), inode=st.st_ino)
        self._resolver = StoreIdResolver()
        self._store_ids_known = True
        return True

    def _read_events(self, fd: int, size: int, max_bytes: int) -> tuple[list[Event], bool]:
        events: list[Event] = []
        start = self._p.offset
        try:
            while True:
                budget = max_bytes - (self._p.offset - start) if events else None
                step = self._step(fd, size, budget)
                if step is _Stop.WAIT:
                    return events, False
                if step is _Stop.FULL:
                    return events, True
                assert not isinstance(step, _Stop)
                events.extend(step)
        except errors.RrdError as exc:
            self._damaged(exc)
            return events, False

    def _damaged(self, exc: errors.RrdError) -> None:
        p = self._p
        p.damaged_at, p.damage = p.offset, str(exc)
        log.warning(
            "%s: %s; the messages before byte %d were imported, the rest is not read until the file is replaced",
            self.path,
            exc,
            p.offset,
        )

    def _step(self, fd: int, size: int, budget: int | None) -> list[Event] | _Stop:
        """The events of the next unit at `offset` (consumed), or why it cannot be read now."""
        if self._p.phase is Phase.STREAM_HEADER:
            return self._stream_header(fd, size)
        if self._p.phase is Phase.MESSAGES:
            return self._message(fd, size, budget)
        return self._footer(fd, size)

    def _stream_header(self, fd: int, size: int) -> list[Event] | _Stop:
        p = self._p
        raw = _pread(fd, STREAM_HEADER_SIZE, p.offset, size)
        if len(raw) < STREAM_HEADER_SIZE:
            if len(raw) >= 4 and not looks_like_stream_header(raw):
                decode_stream_header(raw.ljust(STREAM_HEADER_SIZE, b"\0"), p.offset)  # names what is there
                raise errors.NotAnRrdError(f"expected magic b'RRF2', found {raw[:4]!r}", p.offset)
            return _Stop.WAIT
        header = decode_stream_header(raw, p.offset)
        p.stream_index += 1
        p.stream_offset = p.offset
        p.offset += STREAM_HEADER_SIZE
        p.phase = Phase.MESSAGES
        return [StreamStart(p.stream_offset, p.stream_index, header)]

    def _message(self, fd: int, size: int, budget: int | None) -> list[Event] | _Stop:
        p = self._p
        head = _pread(fd, MESSAGE_HEADER_SIZE, p.offset, size)
        if len(head) >= 4 and looks_like_stream_header(head):  # a stream concatenated without End
            p.phase = Phase.STREAM_HEADER
            return []
        if len(head) < MESSAGE_HEADER_SIZE:
            return _Stop.WAIT
        kind, length = decode_message_header(head)
        if kind > MessageKind.BLUEPRINT_ACTIVATION:
            raise errors.UnknownMessageKindError(f"kind {kind}, expected 0 to 3", p.offset)
        if length > self.max_message_size:
            raise errors.MessageTooLargeError(
                f"{MessageKind(kind).name} message declares {length} bytes, over the limit of {self.max_message_size}",
                p.offset,
            )
        if p.offset + MESSAGE_HEADER_SIZE + length > size:
            return _Stop.WAIT
        if budget is not None and MESSAGE_HEADER_SIZE + length > budget:
            return _Stop.FULL
        raw = _pread(fd, length, p.offset + MESSAGE_HEADER_SIZE, size)
        if len(raw) < length:  # cut while being read: the next read sees the new size
            return _Stop.WAIT
        message = self._decode(fd, kind, raw)
        p.offset += MESSAGE_HEADER_SIZE + length
        if isinstance(message, EndMessage):
            p.phase = Phase.FOOTER
            p.end_start = message.stream_payload_offset
            p.end_length, p.end_crc = length, footer_crc(raw)
        return [message]

    def _footer(self, fd: int, size: int) -> list[Event] | _Stop:
        """The whole stream footer after End at once (entries, then b"RRF2FOOT" and their count)."""
        p = self._p
        pos, entries = p.offset, list[Event]()
        while True:
            head = _pread(fd, FOOTER_FIXED_SIZE, pos, size)
            if len(head) < 8:
                return _Stop.WAIT
            if head[:8] == FOOTER_MAGIC:
                if len(head) < FOOTER_FIXED_SIZE:
                    return _Stop.WAIT
                count = int.from_bytes(head[8:], "little")
                if count != len(entries):
                    raise errors.FooterError(f"stream footer says {count} entries, {len(entries)} precede it", pos)
                p.offset, p.phase = pos + FOOTER_FIXED_SIZE, Phase.STREAM_HEADER
                return entries
            if not entries and looks_like_stream_header(head):  # End without footer, then a new stream
                p.phase = Phase.STREAM_HEADER
                return []
            entry = self._footer_entry(fd, size, pos)
            if entry is None:
                return _Stop.WAIT
            entries.append(entry)
            pos += FOOTER_ENTRY_SIZE

    def _footer_entry(self, fd: int, size: int, pos: int) -> StreamFooter | None:
        p = self._p
        raw = _pread(fd, FOOTER_ENTRY_SIZE, pos, size)
        if int.from_bytes(raw[:8], "little") != p.end_start:
            raise errors.FooterError(
                f"expected a stream footer pointing at byte {p.end_start} of the stream, "
                f"or a new stream; found {raw[:8].hex()}",
                pos,
            )
        if len(raw) < FOOTER_ENTRY_SIZE:
            return None
        start, length, crc = decode_footer_entry(raw)
        if length != p.end_length or crc != p.end_crc:
            raise errors.FooterError(
                f"stream footer (length {length}, CRC {crc:08x}) does not match the End payload "
                f"(length {p.end_length}, CRC {p.end_crc:08x})",
                pos,
            )
        return StreamFooter(pos, p.stream_index, start, length, crc)

    def _decode(self, fd: int, kind: int, raw: bytes) -> Message:
        p = self._p
        where = (p.offset, p.stream_offset, p.stream_index)
        message = self._resolver.complete(decode_message(kind, raw, *where, max_chunk_bytes=self.max_chunk_bytes))
        if not self._store_ids_known and _lacks_application_id(message):
            self._learn_store_ids(fd, p.stream_offset + STREAM_HEADER_SIZE, p.offset)
            message = self._resolver.complete(message)
        return message

    def _learn_store_ids(self, fd: int, start: int, end: int) -> None:
        """Read the SetStoreInfo messages of the current stream before `end` (streams written
        before Rerun 0.25 name a store's application id only there); the rest is skipped."""
        self._store_ids_known = True
        pos = start
        while pos + MESSAGE_HEADER_SIZE <= end:
            kind, length = decode_message_header(_pread(fd, MESSAGE_HEADER_SIZE, pos, end))
            if kind == MessageKind.SET_STORE_INFO and pos + MESSAGE_HEADER_SIZE + length <= end:
                raw = _pread(fd, length, pos + MESSAGE_HEADER_SIZE, end)
                with contextlib.suppress(errors.RrdError):
                    self._resolver.complete(decode_message(kind, raw, pos, self._p.stream_offset))
            pos += MESSAGE_HEADER_SIZE + length


def _lacks_application_id(message: Message) -> bool:
    if isinstance(message, ArrowMessage):
        return not message.store_id.application_id
    if isinstance(message, BlueprintActivationMessage):
        return not message.blueprint_id.application_id
    return False


_MARK_BYTES = 32


def _mark(fd: int, offset: int) -> int:
    if offset == 0:
        return 0
    start = max(0, offset - _MARK_BYTES)
    return xxhash.xxh32_intdigest(_pread(fd, offset - start, start, offset))


def _pread(fd: int, count: int, offset: int, size: int) -> bytes:
    """Up to `count` bytes at `offset`, none past `size` (the size the file had when stat'ed)."""
    count = max(0, min(count, size - offset))
    parts, got = [], 0
    while got < count:
        part = os.pread(fd, count - got, offset + got)
        if not part:
            break
        parts.append(part)
        got += len(part)
    return parts[0] if len(parts) == 1 else b"".join(parts)
