"""Large chunks: their metadata is read from the first bytes of their payload (`chunk.chunk_meta`
through `lz4_prefix`), and what that checks and leaves unchecked.

What a chunk whose values the server reads must pass (full validation) stays: such a chunk is
decompressed whole. A chunk whose values it does not read has its metadata checked as before; its
data columns, as ever, are the viewer's to read, and now so is the LZ4 block past its metadata.
"""

from __future__ import annotations

import io

import lz4.block
import numpy as np
import pyarrow as pa
import pytest

from services.rrd import chunk, errors
from services.rrd.chunk import chunk_meta, read_chunk
from services.rrd.validate import check_chunk
from tests.services.rrd.test_bad_input import CHUNK_ID, LAST_OFFSET, arrow_body, check_error, chunk_ipc, one_arrow

IMAGE_BYTES = 1 << 20


def image_ipc(size: int = IMAGE_BYTES, frames: tuple[int, ...] = (7, 9)) -> bytes:
    """A chunk of `len(frames)` random images (LZ4 cannot shrink them) on a `frame` timeline."""
    rng = np.random.default_rng(3)
    n = len(frames)
    fields = [
        pa.field("rerun.controls.RowId", pa.binary(16), metadata={b"rerun:kind": b"control"}),
        pa.field("frame", pa.int64(), metadata={b"rerun:kind": b"index", b"rerun:index_name": b"frame"}),
        pa.field(
            "Image:buffer",
            pa.list_(pa.list_(pa.uint8())),
            metadata={
                b"rerun:kind": b"data",
                b"rerun:component": b"Image:buffer",
                b"rerun:archetype": b"rerun.archetypes.Image",
            },
        ),
    ]
    images = [[rng.integers(0, 255, size // n, dtype=np.uint8).tolist()] for _ in range(n)]
    columns = [
        pa.array([i.to_bytes(16, "big") for i in range(n)], pa.binary(16)),
        pa.array(frames, pa.int64()),
        pa.array(images, pa.list_(pa.list_(pa.uint8()))),
    ]
    metadata = {
        b"sorbet:version": b"0.1.3",
        b"rerun:entity_path": b"/camera",
        b"rerun:id": b"chunk_" + CHUNK_ID.hex().encode(),
    }
    schema = pa.schema(fields, metadata=metadata)
    sink = io.BytesIO()
    with pa.ipc.new_stream(sink, schema) as writer:
        writer.write_batch(pa.record_batch(columns, schema=schema))
    return sink.getvalue()


@pytest.fixture(scope="module")
def image() -> bytes:
    return image_ipc()


def test_metadata_of_a_large_chunk_from_its_prefix(image: bytes) -> None:
    msg = one_arrow(arrow_body(image))
    assert len(image) >= chunk.PREFIX_FROM_BYTES
    meta = chunk_meta(msg)
    assert (meta.entity_path, meta.num_rows, meta.uncompressed_size) == ("/camera", 2, len(image))
    assert [(t.name, t.range.min, t.range.max) for t in meta.timelines] == [("frame", 7, 9)]
    assert read_chunk(msg).num_rows == 2


def test_damage_within_the_metadata_is_refused(image: bytes) -> None:
    payload = bytearray(lz4.block.compress(image, store_size=False))
    payload[:64] = b"\xff" * 64  # literal lengths that run past the block
    msg = one_arrow(arrow_body(image, payload=bytes(payload)))
    with pytest.raises(errors.RrdError) as info:
        chunk_meta(msg)
    check_error(info.value, errors.DecompressionError, LAST_OFFSET)


def test_a_block_shorter_than_its_metadata_is_refused(image: bytes) -> None:
    payload = lz4.block.compress(image[:2000], store_size=False)
    msg = one_arrow(arrow_body(image, payload=payload, uncompressed_size=len(image)))
    with pytest.raises(errors.RrdError) as info:
        chunk_meta(msg)
    check_error(info.value, errors.DecompressionError, LAST_OFFSET)


def test_past_its_metadata_a_large_chunk_is_still_checked_whole(image: bytes) -> None:
    """A large chunk's metadata is read from the first bytes of its payload, but ingest's check
    decompresses it whole: a block cut after its metadata (which Rerun cannot read) is refused."""
    payload = lz4.block.compress(image, store_size=False)
    msg = one_arrow(arrow_body(image, payload=payload[: len(payload) // 2]))
    meta = chunk_meta(msg)
    assert meta.num_rows == 2 and not meta.values_checked
    with pytest.raises(errors.RrdError) as info:
        check_chunk(msg, meta)
    assert isinstance(info.value, errors.InvalidChunkError) and "does not decompress" in str(info.value)
    with pytest.raises(errors.RrdError) as info:
        read_chunk(msg)
    check_error(info.value, errors.DecompressionError, LAST_OFFSET)


def test_a_large_chunk_is_checked_from_its_body(image: bytes) -> None:
    msg = one_arrow(arrow_body(image))
    meta = chunk_meta(msg)
    assert not meta.values_checked
    check_chunk(msg, meta)  # decompressed whole, and valid


def test_a_large_chunk_whose_values_are_read_is_decompressed_whole() -> None:
    """Scalars: the server reads their values, so a large Scalars chunk is decompressed whole, and
    one whose block does not give its declared size is refused."""
    n = 40_000
    ipc = chunk_ipc(frames=tuple(range(n)), scalars=tuple([float(i)] for i in range(n)))
    assert len(ipc) >= chunk.PREFIX_FROM_BYTES
    meta = chunk_meta(one_arrow(arrow_body(ipc)))
    assert meta.reads_values and meta.num_rows == n and meta.values_checked
    payload = lz4.block.compress(ipc, store_size=False)
    cut = one_arrow(arrow_body(ipc, payload=payload[: len(payload) - 100]))
    with pytest.raises(errors.RrdError) as info:
        chunk_meta(cut)
    check_error(info.value, errors.DecompressionError, LAST_OFFSET)


def test_a_schema_larger_than_the_first_guess(monkeypatch: pytest.MonkeyPatch, image: bytes) -> None:
    """The first bytes decompressed are a guess: a chunk that needs more gets more."""
    monkeypatch.setattr(chunk, "_prefix_guess", 16)
    meta = chunk_meta(one_arrow(arrow_body(image)))
    assert meta.num_rows == 2 and [t.range.max for t in meta.timelines] == [9]
