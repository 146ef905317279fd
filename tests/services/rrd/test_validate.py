"""Chunks Rerun refuses are refused before any value is read (services/rrd/validate.py, conformance.py).

Each malformed variant of tests/services/rrd/malformed.py is written into an .rrd file that the real
`rerun rrd verify` (0.41) must reject; our validation must reject the chunk too, naming it (chunk id,
entity, byte offset), without reading out of bounds.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pyarrow as pa
import pytest

from services.facts.identity import read_property_chunk
from services.rrd import conformance, errors
from services.rrd.chunk import chunk_meta, read_chunk
from services.rrd.decoder import decode_message
from services.rrd.messages import ArrowMessage, chunk_id_str
from services.rrd.validate import check_chunk, validated_batch
from tests.services.rrd.malformed import (
    MALFORMED,
    Seed,
    i32,
    ipc_of,
    malformed_chunk,
    node_length_patched,
    record_seed,
    rerun_verify,
    wrap,
)

pytestmark = pytest.mark.sdk


@pytest.fixture(scope="module")
def seed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Seed]:
    yield Seed.read(record_seed(tmp_path_factory.mktemp("seed") / "seed.rrd"))


def _ingest_checks(msg: ArrowMessage) -> None:
    """What ingest does with a chunk before filing it."""
    meta = chunk_meta(msg)
    check_chunk(msg, meta)
    if meta.entity_path.startswith("/__properties"):
        read_property_chunk(msg, meta)


def test_the_intact_seed_passes_both(seed: Seed, rerun_bin: str, tmp_path: Path) -> None:
    path = tmp_path / "seed.rrd"
    path.write_bytes(seed.stream())
    assert rerun_verify(rerun_bin, path).returncode == 0
    chunks = [e for e in seed.events if isinstance(e, ArrowMessage)]
    for msg in chunks:
        _ingest_checks(msg)
        assert chunk_meta(msg).problem is None
    assert sum(chunk_meta(m).reads_values for m in chunks) == 3  # scalars, text log, transform


@pytest.mark.parametrize("variant", MALFORMED)
def test_rerun_refuses_the_variant(seed: Seed, variant: str, rerun_bin: str, tmp_path: Path) -> None:
    msg, raw = malformed_chunk(seed, variant)
    path = tmp_path / f"{variant}.rrd"
    path.write_bytes(seed.stream({msg.offset: raw}))
    verified = rerun_verify(rerun_bin, path)
    assert verified.returncode != 0, f"rerun rrd verify accepts {variant}: {verified.stderr}"


@pytest.mark.parametrize("variant", MALFORMED)
def test_ingest_refuses_the_variant(seed: Seed, variant: str) -> None:
    original, raw = malformed_chunk(seed, variant)
    msg = decode_message(2, raw, original.offset)
    assert isinstance(msg, ArrowMessage)
    with pytest.raises(errors.RrdError) as info:
        _ingest_checks(msg)
    exc = info.value
    assert exc.offset == original.offset and exc.http_status() == 400 and exc.grpc_status() == "INVALID_ARGUMENT"
    if isinstance(exc, errors.InvalidChunkError):
        assert original.chunk_id is not None
        assert chunk_id_str(original.chunk_id) in str(exc)
        assert f"entity {MALFORMED[variant][0]}" in str(exc)
    else:  # refused while its metadata is read (not even an index Rerun accepts)
        assert isinstance(exc, errors.NotAChunkError), exc


@pytest.mark.parametrize(
    "variant", [v for v in MALFORMED if not v.startswith(("row_id_missing", "row_id_binary", "no_chunk_id", "index_"))]
)
def test_every_value_reader_validates_first(seed: Seed, variant: str) -> None:
    """validated_batch (used by analytics extraction and exact trimming) refuses every variant whose
    values are wrong (the others are refused by ingest from their schema)."""
    original, raw = malformed_chunk(seed, variant)
    msg = decode_message(2, raw, original.offset)
    assert isinstance(msg, ArrowMessage)
    with pytest.raises(errors.RrdError):
        validated_batch(msg)


def test_types_compare_without_nested_names_or_nullability() -> None:
    """Rerun accepts `list<x: double>` and non-null items for Scalars (checked with rrd verify)."""
    expected = conformance.READ_COMPONENTS["Scalars:scalars"]
    assert conformance.same_type(pa.list_(pa.field("x", pa.float64(), nullable=False)), expected)
    assert not conformance.same_type(pa.list_(pa.float32()), expected)
    translation = conformance.READ_COMPONENTS["Transform3D:translation"]
    assert conformance.same_type(pa.list_(pa.list_(pa.float32(), 3)), translation)
    assert not conformance.same_type(pa.list_(pa.list_(pa.float32(), 2)), translation)
    assert not conformance.same_type(pa.list_(pa.list_(pa.float32())), translation)
    axis_angle = conformance.READ_COMPONENTS["Transform3D:rotation_axis_angle"]
    assert conformance.same_type(
        pa.list_(pa.struct([("axis", pa.list_(pa.float32(), 3)), ("angle", pa.float32())])), axis_angle
    )
    assert not conformance.same_type(
        pa.list_(pa.struct([("angle", pa.float32()), ("axis", pa.list_(pa.float32(), 3))])), axis_angle
    )


def test_scalars_checked_without_pyarrow_only_when_pyarrow_agrees(seed: Seed) -> None:
    """Ingest checks Scalars offsets from the batch header (no pyarrow read); whenever it says a
    chunk is valid, pyarrow's full validation must agree. Every offset and the values node length
    are set to boundary values in turn."""
    msg = seed.chunk("/robot/speed")
    assert chunk_meta(msg).values_checked  # the common case takes the fast path
    batch = read_chunk(msg)
    intact = ipc_of(batch)
    offsets_at = intact.index(i32(0, 2, 4, 6, 8))
    variants: list[bytes] = []
    for slot in range(5):
        for value in (-1, 0, 1, 3, 5, 7, 8, 9, 1 << 20, -(1 << 31)):
            edited = bytearray(intact)
            edited[offsets_at + 4 * slot : offsets_at + 4 * slot + 4] = i32(value)
            variants.append(bytes(edited))
    variants += [node_length_patched(batch, 4, n) for n in (0, 1, 7, 9, 1 << 20)]  # the values' node
    checked = 0
    for variant in variants:
        damaged = decode_message(2, wrap(msg, variant), msg.offset)
        assert isinstance(damaged, ArrowMessage)
        try:
            meta = chunk_meta(damaged)
        except errors.RrdError:
            continue
        if meta.values_checked:
            checked += 1
            read_chunk(damaged).validate(full=True)  # raises if the fast check let a bad chunk through
        else:
            with pytest.raises(errors.RrdError):
                check_chunk(damaged, meta)
    assert checked >= 5  # the harmless variants (e.g. an offset moved within its neighbours)
