"""LZ4 blocks and Arrow IPC from outside the depot: the one way the server reads them.

Clients send Arrow IPC (LZ4-compressed or not) on every surface: chunks over gRPC and in uploads
(relayed between nodes as they came), and tables in the catalog service's requests (FetchChunks'
`chunk_infos`). Both formats let a few bytes claim a lot: an LZ4 block may declare 255x its size
(or anything, and fail late), an IPC record batch may compress its buffers and declare any size
for them, and pyarrow's cheap validation only compares buffer sizes with lengths, so a list or
binary offset pointing past its data passes it and reading that value goes out of bounds (a
crash of the whole process, every live stream with it). So here, and nowhere else:

- an LZ4 block's declared size is checked against the process's chunk limit
  (FLEET_MAX_CHUNK_BYTES) and LZ4's largest ratio before anything is allocated, and the block must
  decompress to exactly that size (`decompress`);
- an IPC stream whose record batches compress their buffers is refused before pyarrow reads it
  (Rerun never writes them; pyarrow would allocate what they declare), and every batch is fully
  validated (offsets within their data, UTF-8, children long enough) before any value is read
  (`read_table`).

Chunks are read by `services.rrd.chunk` (their metadata, without copying their columns) and
checked in full by `services.rrd.validate.check_chunk`, on the same two functions.
tests/services/rrd/test_untrusted.py pins that no module outside the codec reads Arrow IPC or LZ4,
and tests/services/test_client_inputs.py sends hostile inputs to every RPC that carries them.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager

import lz4.block
import pyarrow as pa

from services.rrd import errors, limits, lz4_prefix

LZ4_MAX_RATIO = 255  # no LZ4 block expands more than ~255x (plus a few bytes)
_RECORD_BATCH, _DICTIONARY_BATCH = 3, 4  # flatbuffers MessageHeader union tags


def check_declared_size(declared: int, compressed: int, offset: int = 0) -> None:
    """Refuse, before anything is allocated, an LZ4 block declaring more than the chunk limit or
    more than its bytes can decompress to."""
    if declared > limits.max_chunk_bytes():
        raise errors.MessageTooLargeError(
            f"declares {declared} bytes uncompressed, over the limit of {limits.max_chunk_bytes()} "
            "(raise FLEET_MAX_CHUNK_BYTES if data this large is expected)",
            offset,
        )
    if declared < 0 or declared > LZ4_MAX_RATIO * compressed + 64:
        raise errors.DecompressionError(
            f"LZ4 block of {compressed} bytes cannot decompress to the declared {declared} bytes", offset
        )


def decompress(block: bytes | bytearray | memoryview, declared: int, offset: int = 0) -> bytes:
    """The bytes an LZ4 block holds, once its declared size is known to be acceptable; raises
    DecompressionError unless it decompresses to exactly `declared` bytes."""
    check_declared_size(declared, len(block), offset)
    try:
        data: bytes = lz4.block.decompress(block, uncompressed_size=declared)
    except (lz4.block.LZ4BlockError, ValueError, MemoryError, OverflowError) as exc:
        raise errors.DecompressionError(
            f"LZ4 block of {len(block)} bytes does not decompress to the declared {declared} bytes ({exc})", offset
        ) from exc
    if len(data) != declared:
        raise errors.DecompressionError(f"LZ4 block decompressed to {len(data)} bytes, declared {declared}", offset)
    return data


@contextmanager
def decompressed_view(
    block: bytes | bytearray | memoryview, declared: int, offset: int = 0
) -> Iterator[bytes | memoryview]:
    """What `decompress` gives, for a reader that checks the bytes and drops them: a view of a buffer
    reused by this thread (no allocation per block), valid inside the block only."""
    check_declared_size(declared, len(block), offset)
    if not lz4_prefix.available or declared == 0:
        yield decompress(block, declared, offset)
        return
    with ExitStack() as stack:
        try:
            data = stack.enter_context(lz4_prefix.decompress_into(block, declared))
        except ValueError as exc:
            raise errors.DecompressionError(
                f"LZ4 block of {len(block)} bytes does not decompress to the declared {declared} bytes ({exc})",
                offset,
            ) from exc
        yield data


def body_compressed(message: pa.ipc.Message) -> bool:
    """Whether an IPC record batch (or dictionary batch) message compresses its buffers: read
    from its flatbuffer header (Message: 1 header_type, 2 header; RecordBatch: 3 compression;
    DictionaryBatch: 1 data, a RecordBatch)."""
    if message.type not in ("record batch", "dictionary batch"):
        return False
    meta = message.metadata.to_pybytes()
    root = int.from_bytes(meta[0:4], "little")
    header = _field(meta, root, 2)
    if header is None:
        return False
    if message.type == "dictionary batch":
        header = _field(meta, header, 1)
        if header is None:
            return False
    return _field(meta, header, 3) is not None


def _field(buf: bytes, table: int, slot: int) -> int | None:
    """Where the table an offset field of a flatbuffers table points to starts (None: unset).
    pyarrow's flatbuffers verifier checked the message; out of bounds anyway: ValueError."""
    vtable = table - _int(buf, table, 4, signed=True)
    if _int(buf, vtable, 2) < 6 + 2 * slot:
        return None
    field_offset = _int(buf, vtable + 4 + 2 * slot, 2)
    if not field_offset:
        return None
    at = table + field_offset
    return at + _int(buf, at, 4)


def _int(buf: bytes, at: int, size: int, signed: bool = False) -> int:
    if not 0 <= at <= len(buf) - size:
        raise ValueError("flatbuffers offset out of bounds")
    return int.from_bytes(buf[at : at + size], "little", signed=signed)


def read_table(data: bytes | pa.Buffer, offset: int = 0) -> pa.Table:
    """The table an Arrow IPC stream holds, fully validated; NotArrowError otherwise."""
    buffer = data if isinstance(data, pa.Buffer) else pa.py_buffer(data)
    try:
        messages = pa.ipc.MessageReader.open_stream(buffer)
        for message in messages:
            if body_compressed(message):
                raise errors.NotArrowError(
                    "its record batches compress their buffers (IPC body compression), which Rerun never "
                    "writes: send them uncompressed (the whole payload may be LZ4)",
                    offset,
                )
        table = pa.ipc.open_stream(buffer).read_all()
        table.validate(full=True)
    except (pa.ArrowException, OSError, EOFError, ValueError) as exc:  # pyarrow's IO errors are OSErrors
        raise errors.NotArrowError(f"not a valid Arrow IPC stream ({exc})", offset) from exc
    return table


def payload_table(compressed: bool, payload: bytes, declared: int, offset: int = 0) -> pa.Table:
    """A table sent as an Arrow IPC stream, LZ4-compressed as a block or not."""
    return read_table(decompress(payload, declared, offset) if compressed else payload, offset)
