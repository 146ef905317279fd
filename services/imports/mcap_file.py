"""What the depot reads of an MCAP file itself, before the Rerun CLI converts it: that it is one
(magic bytes at both ends, a footer, a summary the `mcap` library reads), its identity (content
digest), where its data section ends, and the metadata records that name its run or robot.

The data section matters for a recording written in steps (MCAP's append mode rewrites the file
from its DataEnd record on): a file whose bytes before its DataEnd record are a longer file's first
bytes is an earlier copy of that recording, and the longer one adds only the messages after them.
"""

from __future__ import annotations

import hashlib
import io
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

import lz4.frame
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Chunk, ChunkIndex, Metadata

from core.errors import ConversionLimitError, FleetError, InvalidMcapError

MAGIC = b"\x89MCAP0\r\n"
FOOTER_RECORD = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, summary_crc
DATA_END_RECORD = 1 + 8 + 4  # opcode, length, data_section_crc
HEAD_BYTES = 4096  # the first bytes whose digest finds earlier copies of a recording (header, first chunk)
MAX_SUMMARY_BYTES = 256 << 20  # a bag of 50 GB holds a few MB of summary
MAX_METADATA_BYTES = 1 << 20
READ_BYTES = 8 << 20
RUN_KEYS = {"fleet": "run_id"}  # metadata record -> key naming the run
ROBOT_KEYS = {"fleet": "robot_id", "foxglove": "deviceName"}  # -> key naming the robot (first found)


def is_mcap(head: bytes) -> bool:
    """Whether a file's first bytes are MCAP's magic."""
    return head.startswith(MAGIC)


@dataclass(frozen=True)
class McapFacts:
    size: int
    data_end: int  # where the DataEnd record (or the summary) begins: the data section's length
    head_digest: str | None  # sha256 of the first HEAD_BYTES bytes; None if its data section is shorter
    messages: int
    topics: tuple[str, ...]
    start_ns: int | None
    end_ns: int | None
    profile: str
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)

    def named(self, keys: dict[str, str]) -> str | None:
        """The first value of a (record, key) pair of `keys` the file's metadata holds."""
        for record, key in keys.items():
            value = self.metadata.get(record, {}).get(key)
            if value:
                return value
        return None


def inspect(path: Path) -> McapFacts:
    """The facts of a complete MCAP file; InvalidMcapError naming what is wrong otherwise."""
    size = path.stat().st_size
    try:
        with open(path, "rb") as f:
            return _inspect(f, size)
    except FleetError:
        raise
    except (McapError, ValueError, KeyError, IndexError, struct.error, EOFError, UnicodeDecodeError) as exc:
        raise InvalidMcapError(f"the MCAP file cannot be read ({type(exc).__name__}: {str(exc)[:200]})") from None


def _inspect(f: BinaryIO, size: int) -> McapFacts:
    if size < 2 * len(MAGIC) + FOOTER_RECORD:
        raise InvalidMcapError(f"the file is {size} bytes: too short to be an MCAP file")
    if f.read(len(MAGIC)) != MAGIC:
        raise InvalidMcapError("the file does not begin with MCAP's magic bytes")
    f.seek(size - len(MAGIC))
    if f.read(len(MAGIC)) != MAGIC:
        raise InvalidMcapError(
            "the file does not end with MCAP's magic bytes: it is truncated (the recorder did not close it). "
            "Upload it once the recording is closed, or repair it first with `mcap recover`"
        )
    summary_start = _summary_start(f, size)
    if summary_start and size - summary_start > MAX_SUMMARY_BYTES:
        raise InvalidMcapError(f"the summary section is {size - summary_start:,} bytes: more than an MCAP file needs")
    data_end = _data_end(f, summary_start or size - len(MAGIC) - FOOTER_RECORD)
    f.seek(0)
    reader = make_reader(f)
    header = reader.get_header()
    summary = reader.get_summary()
    if summary is None:
        raise InvalidMcapError("the file has no summary section (no chunk index): repair it first with `mcap recover`")
    stats = summary.statistics
    return McapFacts(
        size=size,
        data_end=data_end,
        head_digest=digest_of(f, HEAD_BYTES) if data_end >= HEAD_BYTES else None,
        messages=stats.message_count if stats else 0,
        topics=tuple(sorted({c.topic for c in summary.channels.values()})),
        start_ns=stats.message_start_time if stats and stats.message_count else None,
        end_ns=stats.message_end_time if stats and stats.message_count else None,
        profile=header.profile,
        metadata=_metadata(f, summary),
    )


def _summary_start(f: BinaryIO, size: int) -> int:
    f.seek(size - len(MAGIC) - FOOTER_RECORD)
    record = f.read(FOOTER_RECORD)
    opcode, length, summary_start, _, _ = struct.unpack("<BQQQI", record)
    if opcode != Opcode.FOOTER or length != 20:
        raise InvalidMcapError("the file has no valid footer before its closing magic: it is corrupt")
    if summary_start >= size:
        raise InvalidMcapError("the footer points past the end of the file: it is corrupt")
    return int(summary_start)


def _data_end(f: BinaryIO, end: int) -> int:
    """The DataEnd record's offset, which precedes the summary (or the footer); `end` if absent."""
    at = end - DATA_END_RECORD
    if at >= len(MAGIC):
        f.seek(at)
        opcode, length = struct.unpack("<BQ", f.read(9))
        if opcode == Opcode.DATA_END and length == 4:
            return at
    return end


def _metadata(f: BinaryIO, summary: object) -> dict[str, dict[str, str]]:
    """The metadata records the depot reads (run, robot), each at most MAX_METADATA_BYTES."""
    found: dict[str, dict[str, str]] = {}
    wanted = set(RUN_KEYS) | set(ROBOT_KEYS)
    for index in getattr(summary, "metadata_indexes", []):
        if index.name not in wanted or index.length > MAX_METADATA_BYTES or index.name in found:
            continue
        f.seek(index.offset)
        record = f.read(index.length)
        if len(record) != index.length or record[0] != Opcode.METADATA:
            continue
        found[index.name] = _metadata_map(record[9:])
    return found


def _metadata_map(body: bytes) -> dict[str, str]:
    """A Metadata record's body as its map of strings (the `mcap` library's reader)."""
    return dict(Metadata.read(ReadDataStream(io.BytesIO(body))).metadata)


def digest_of(f: BinaryIO, length: int) -> str:
    """sha256 of the first `length` bytes of `f`."""
    return digests_at(f, (length,))[length]


def digests_at(f: BinaryIO, offsets: tuple[int, ...]) -> dict[int, str]:
    """sha256 of the first `n` bytes of `f` for each n in `offsets`, in one pass."""
    wanted = sorted(set(offsets))
    found: dict[int, str] = {}
    hasher, position = hashlib.sha256(), 0
    f.seek(0)
    for offset in wanted:
        while position < offset:
            piece = f.read(min(READ_BYTES, offset - position))
            if not piece:
                return found  # the file is shorter: no digest at or after this offset
            hasher.update(piece)
            position += len(piece)
        found[offset] = hasher.copy().hexdigest()
    return found


def check_chunks(path: Path, max_chunk_bytes: int) -> None:
    """Every chunk the summary indexes decompressed and checked against its CRC, one at a time: the
    Rerun CLI spins without end on some corrupt chunks, and a chunk that inflates past what a
    conversion may use is refused before it is tried. InvalidMcapError or ConversionLimitError
    naming the chunk's offset."""
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
            size = path.stat().st_size
            for index in summary.chunk_indexes if summary is not None else ():
                _check_chunk(f, size, index, max_chunk_bytes)
    except FleetError:
        raise
    except Exception as exc:  # a codec's own error on hostile bytes: zstd, lz4, struct
        raise InvalidMcapError(f"a chunk of the file cannot be read ({type(exc).__name__}: {str(exc)[:200]})") from None


def _check_chunk(f: BinaryIO, size: int, index: ChunkIndex, max_chunk_bytes: int) -> None:
    at = index.chunk_start_offset
    if not len(MAGIC) <= at < at + index.chunk_length <= size:
        # before reading it: a read of the length an index claims allocates all of it at once
        raise InvalidMcapError(
            f"the chunk index points at bytes {at:,} to {at + index.chunk_length:,}, outside the file's "
            f"{size:,} bytes: the file is corrupt"
        )
    if index.uncompressed_size > max_chunk_bytes:
        raise ConversionLimitError(
            f"the chunk at byte {at} inflates to {index.uncompressed_size:,} bytes: more than a conversion may use "
            f"({max_chunk_bytes:,} bytes, half of FLEET_MCAP_MEMORY_MB)"
        )
    f.seek(at)
    record = f.read(index.chunk_length)
    if len(record) != index.chunk_length or record[0] != Opcode.CHUNK:
        raise InvalidMcapError(f"the chunk index points at byte {at}, where there is no chunk: the file is corrupt")
    chunk = Chunk.read(ReadDataStream(io.BytesIO(record[9:])))
    if chunk.uncompressed_size != index.uncompressed_size:
        raise InvalidMcapError(f"the chunk at byte {at} disagrees with its index on its size: the file is corrupt")
    try:
        data = _inflate(chunk)
    except FleetError:
        raise
    except Exception as exc:  # the codec's own error on hostile bytes
        raise InvalidMcapError(f"the chunk at byte {at} is corrupt ({type(exc).__name__}: {str(exc)[:200]})") from None
    if len(data) != chunk.uncompressed_size or (chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc):
        raise InvalidMcapError(f"the chunk at byte {at} is corrupt (its size or CRC does not match its contents)")
    _check_records(data, at)


def _inflate(chunk: Chunk) -> bytes:
    """A chunk's records, never more than the size it states (a codec told so stops there)."""
    size = chunk.uncompressed_size
    if chunk.compression == "zstd":
        return bytes(zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=size))
    if chunk.compression == "lz4":
        decompressor = lz4.frame.LZ4FrameDecompressor()
        data = bytes(decompressor.decompress(chunk.data, max_length=size + 1))
        if not decompressor.eof:
            raise InvalidMcapError("an lz4 chunk holds more than the size it states, or is cut")
        return data
    if chunk.compression == "":
        return bytes(chunk.data)
    raise InvalidMcapError(f"a chunk is compressed with {chunk.compression[:20]!r}: MCAP allows zstd, lz4 or none")


def _check_records(data: bytes, at: int) -> None:
    """Each record inside a chunk fits in it: the converter trusts a record's length and would
    allocate what a hostile one claims."""
    position, end = 0, len(data)
    while position < end:
        if position + 9 > end:
            raise InvalidMcapError(f"the chunk at byte {at} ends inside a record header: the file is corrupt")
        length = int.from_bytes(data[position + 1 : position + 9], "little")
        if length > end - position - 9:
            raise InvalidMcapError(
                f"a record inside the chunk at byte {at} claims {length:,} bytes, more than the chunk holds: "
                "the file is corrupt"
            )
        position += 9 + length
