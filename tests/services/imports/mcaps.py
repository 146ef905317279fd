"""MCAP files for the import tests, written with the `mcap` library: a JSON channel of known values,
a recording written further (the same first chunks, then more), and hostile files."""

from __future__ import annotations

import json
import zlib
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

T0 = 1_700_000_000_000_000_000
SCHEMA = json.dumps({"type": "object", "properties": {"value": {"type": "number"}}}).encode()


def json_mcap(
    path: Path,
    messages: int,
    *,
    topics: tuple[str, ...] = ("/sensors/temp",),
    metadata: dict[str, dict[str, str]] | None = None,
    chunk_size: int = 64 * 1024,
    first: int = 0,
    compression: CompressionType = CompressionType.ZSTD,
) -> Path:
    """`messages` messages on each topic, the k-th with value k/2 at T0 + k*10 ms; metadata records first.
    With chunk_size=1 every message is a chunk of its own, so a file of more messages begins with
    exactly the bytes of one of fewer (up to its DataEnd record), as a recording written further."""
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=chunk_size, compression=compression)
        writer.start(profile="", library="fleet-tests")
        for name, values in (metadata or {}).items():
            writer.add_metadata(name, values)
        schema = writer.register_schema("Reading", "jsonschema", SCHEMA)
        channels = [writer.register_channel(t, "json", schema) for t in topics]
        for k in range(first, messages):
            for channel in channels:
                data = json.dumps({"value": k / 2}).encode()
                writer.add_message(channel, log_time=T0 + k * 10_000_000, data=data, publish_time=T0, sequence=k)
        writer.finish()
    return path


def truncated(source: Path, target: Path, keep: float = 0.6) -> Path:
    data = source.read_bytes()
    target.write_bytes(data[: int(len(data) * keep)])
    return target


def corrupt(source: Path, target: Path) -> Path:
    """The file with bytes in the middle of its first chunk's compressed records overwritten (its
    structure, summary and indexes intact)."""
    data = bytearray(source.read_bytes())
    with open(source, "rb") as f:
        first = make_reader(f).get_summary().chunk_indexes[0]  # type: ignore[union-attr]
    middle = first.chunk_start_offset + first.chunk_length // 2
    data[middle : middle + 64] = bytes(255 - b for b in data[middle : middle + 64])
    target.write_bytes(bytes(data))
    return target


def bomb(path: Path, inflated: int) -> Path:
    """A small MCAP whose one message is `inflated` bytes of JSON that compress to almost nothing:
    converting it needs at least that much memory."""
    data = b'{"value": "' + b"0" * inflated + b'"}'
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile="", library="fleet-tests")
        schema = writer.register_schema("Reading", "jsonschema", SCHEMA)
        channel = writer.register_channel("/bomb", "json", schema)
        writer.add_message(channel, log_time=T0, data=data, publish_time=T0)
        del data
        writer.finish()
    return path


def hostile_record(source_messages: int, path: Path) -> Path:
    """A valid uncompressed MCAP whose first chunk's first record claims 2 GiB, with the chunk's
    CRC made to match: only a walk of the records inside the chunk finds it."""
    json_mcap(path, source_messages, compression=CompressionType.NONE)
    data = bytearray(path.read_bytes())
    with open(path, "rb") as f:
        first = make_reader(f).get_summary().chunk_indexes[0]  # type: ignore[union-attr]
    header = first.chunk_start_offset + 9
    compression_len = int.from_bytes(data[header + 28 : header + 32], "little")
    records = header + 32 + compression_len + 8
    records_len = int.from_bytes(data[records - 8 : records], "little")
    data[records + 1 : records + 9] = (2 << 30).to_bytes(8, "little")
    crc = zlib.crc32(bytes(data[records : records + records_len]))
    data[header + 24 : header + 28] = crc.to_bytes(4, "little")
    path.write_bytes(bytes(data))
    return path
