"""Reading a growing hot run's chunk index a piece at a time: the entries appended since the last
read, without parsing the index again from its start.

A follower that sends a run on as it is written (the robot agent forwarding its spool) reads the
index file from where it stopped; what the index does not hold (a message written without its
record, a damaged record) is read from the run file itself, as `read_hot_index` does. Each entry
comes once, in file order; entries before `start` are skipped (a follower resuming mid-run).
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import pyarrow as pa

from services.hot.index import INDEX_FILE, MAGIC, HotEntry, index_records, parse_record, scan_run_file
from services.rrd import errors as rrd_errors
from services.rrd.frames import STREAM_HEADER_SIZE
from services.rrd.layout import ChunkLayout

log = logging.getLogger(__name__)

_READ_BYTES = 4 << 20


class HotIndexTail:
    """The entries of one run file from `start` on, as the file grows. Not thread-safe: one reader."""

    def __init__(self, run_file: Path, start: int = STREAM_HEADER_SIZE) -> None:
        self.run_file = run_file
        self.start = start
        self.covered = STREAM_HEADER_SIZE  # run file offset of the next frame
        self._index_pos = len(MAGIC)  # where the next unread record starts in the index file
        self._layouts: dict[int, tuple[ChunkLayout, list[str]]] = {}
        self._index_usable = True  # False once the index disagrees: the rest is read from the run file
        self._read_bytes = _READ_BYTES  # grows when a single record is larger

    @property
    def position(self) -> int:
        """Run file offset up to which entries were returned (or skipped)."""
        return max(self.covered, self.start)

    def read(self, size: int, limit: int = 4096) -> list[HotEntry]:
        """Entries of the whole frames between the last read and `size` (at most `limit` of them)."""
        entries: list[HotEntry] = []
        if self._index_usable:
            self._from_index(size, limit, entries)
        if self.covered < size and len(entries) < limit:
            for entry in scan_run_file(self.run_file, self.covered, size)[: limit - len(entries)]:
                self._take(entry, entries)
        return entries

    def _from_index(self, size: int, limit: int, entries: list[HotEntry]) -> None:
        try:
            with open(self.run_file.with_name(INDEX_FILE), "rb") as fh:
                if self._index_pos == len(MAGIC) and fh.read(len(MAGIC)) != MAGIC:
                    self._index_usable = False
                    return
                fh.seek(self._index_pos)
                data = fh.read(self._read_bytes)
        except OSError:
            self._index_usable = False
            return
        base = self._index_pos - len(MAGIC)  # `index_records` counts positions after the magic
        records = list(index_records(MAGIC + data))
        if not records and len(data) == self._read_bytes:
            self._read_bytes *= 2  # a record larger than a read: take more
            self._from_index(size, limit, entries)
            return
        for end, payload in records:
            try:
                entry = parse_record(payload, self._layouts)
            except (struct.error, IndexError, KeyError, ValueError, pa.ArrowException, rrd_errors.RrdError) as exc:
                log.warning("chunk index of %s is damaged (%s): reading on from the run file", self.run_file, exc)
                self._index_usable = False
                return
            if entry is not None and entry.end <= self.covered:
                # read from the run file while the index lagged behind it (ingest writes a message,
                # then its record): skipped, so the index serves what follows
                self._index_pos = base + end
                continue
            if entry is not None and (entry.offset != self.covered or entry.end > size):
                if entry.offset != self.covered:
                    self._index_usable = False  # not the next frame: the index no longer follows the file
                return  # past `size`: read again next time
            self._index_pos = base + end
            if entry is not None:
                self._take(entry, entries)
                if len(entries) >= limit:
                    return

    def _take(self, entry: HotEntry, entries: list[HotEntry]) -> None:
        self.covered = entry.end
        if entry.offset >= self.start:
            entries.append(entry)
