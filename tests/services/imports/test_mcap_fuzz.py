"""MCAP bytes made hostile by hypothesis: whatever a file's bytes are, what the depot reads of it
itself (its facts, its chunks) either reads it or refuses it with one of the two errors an upload
answers with (400 INVALID_MCAP, 413 CONVERSION_LIMIT), never another exception: the converter is
only given a file these checks passed."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType

from core.errors import ConversionLimitError, InvalidMcapError
from services.imports.mcap_file import check_chunks, inspect
from tests.services.imports.mcaps import json_mcap

MAX_CHUNK_BYTES = 1 << 20


@pytest.fixture(scope="module")
def originals(tmp_path_factory: pytest.TempPathFactory) -> dict[CompressionType, bytes]:
    """Small files of many chunks, one per compression, with the metadata records the depot reads."""
    folder = tmp_path_factory.mktemp("mcaps")
    made = {}
    for compression in (CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE):
        path = json_mcap(
            folder / f"{compression.name}.mcap",
            60,
            topics=("/a", "/b"),
            metadata={"fleet": {"run_id": "run-1", "robot_id": "r7"}},
            chunk_size=512,
            compression=compression,
        )
        made[compression] = path.read_bytes()
    return made


# a change to the bytes: overwrite some at a place, cut the file there, or repeat a stretch of it
edits = st.one_of(
    st.tuples(st.just("overwrite"), st.floats(0, 1), st.binary(min_size=1, max_size=16)),
    st.tuples(st.just("cut"), st.floats(0, 1), st.just(b"")),
    st.tuples(st.just("repeat"), st.floats(0, 1), st.integers(1, 300).map(lambda n: n.to_bytes(2, "little"))),
)


def edited(data: bytes, changes: list[tuple[str, float, bytes]]) -> bytes:
    out = bytearray(data)
    for kind, where, value in changes:
        at = min(int(where * len(out)), max(len(out) - 1, 0))
        if kind == "overwrite":
            out[at : at + len(value)] = value
        elif kind == "cut":
            del out[at:]
        else:
            stretch = out[at : at + int.from_bytes(value, "little")]
            out[at:at] = stretch
    return bytes(out)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    compression=st.sampled_from([CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE]),
    changes=st.lists(edits, min_size=1, max_size=4),
    near_the_end=st.booleans(),
)
def test_hostile_bytes_are_read_or_refused_as_invalid_mcap(
    originals: dict[CompressionType, bytes],
    tmp_path: Path,
    compression: CompressionType,
    changes: list[tuple[str, float, bytes]],
    near_the_end: bool,
) -> None:
    data = originals[compression]
    if near_the_end:  # the footer, summary and its indexes: where a reader is told where to look
        changes = [(kind, 0.85 + where * 0.15, value) for kind, where, value in changes]
    path = tmp_path / "hostile.mcap"
    path.write_bytes(edited(data, changes))
    try:
        facts = inspect(path)
        check_chunks(path, MAX_CHUNK_BYTES)
    except (InvalidMcapError, ConversionLimitError) as refused:
        assert refused.message and "\n" not in refused.message
        return
    assert facts.size == path.stat().st_size and facts.messages >= 0
    assert facts.data_end <= facts.size
