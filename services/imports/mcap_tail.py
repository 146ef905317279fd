"""The part of an MCAP file a held copy of the same recording lacks, as an MCAP file of its own.

A recording written in steps (MCAP's append mode) keeps its earlier bytes up to its DataEnd record;
when the depot holds that earlier copy, the new file's records after the earlier data section are
exactly the messages the depot lacks. They are copied, with every schema and channel of the file,
into a new MCAP by the `mcap` library's reader and writer, and that file alone is converted.
"""

from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

from core.errors import InvalidMcapError

RECORD_LIMIT = 1 << 30  # a record larger than this is refused: the converter's own limit is lower


class _Window:
    """`length` bytes of `f` from where it stands, as a stream the reader stops at."""

    def __init__(self, f: BinaryIO, length: int) -> None:
        self._f, self._left = f, length

    def read(self, n: int = -1) -> bytes:
        want = self._left if n is None or n < 0 else min(n, self._left)
        data = self._f.read(want)
        self._left -= len(data)
        return data


def write_tail(source: Path, start: int, end: int, target: Path) -> int:
    """Write the messages of `source`'s records in [start, end) to `target`; how many."""
    count = 0
    with open(source, "rb") as f, open(target, "wb") as out:
        reader = make_reader(f)
        header, summary = reader.get_header(), reader.get_summary()
        if summary is None:
            raise InvalidMcapError("the file has no summary section: its schemas and channels are unknown")
        writer = Writer(out)
        writer.start(header.profile, header.library)
        schemas = {
            sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in sorted(summary.schemas.items())
        }
        channels = {
            cid: writer.register_channel(c.topic, c.message_encoding, schemas.get(c.schema_id, 0), c.metadata)
            for cid, c in sorted(summary.channels.items())
        }
        f.seek(start)
        records = StreamReader(_Window(f, end - start), skip_magic=True, record_size_limit=RECORD_LIMIT).records  # type: ignore[arg-type]
        try:
            for record in records:
                if isinstance(record, Message) and record.channel_id in channels:
                    writer.add_message(
                        channels[record.channel_id], record.log_time, record.data, record.publish_time, record.sequence
                    )
                    count += 1
        except EndOfFile:
            pass  # the window ends at the data section's end: no record is cut, the reader only looks past it
        writer.finish()  # type: ignore[no-untyped-call]
    return count
