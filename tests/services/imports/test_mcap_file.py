"""What the depot reads of an MCAP file itself: its facts, where its data section ends, digests at
offsets, the messages a held copy lacks."""

from __future__ import annotations

import hashlib
from pathlib import Path

import pytest
from mcap.reader import make_reader

from core.errors import ConversionLimitError, InvalidMcapError
from services.imports.mcap_file import MAGIC, check_chunks, digests_at, inspect, is_mcap
from services.imports.mcap_tail import write_tail
from tests.services.imports.mcaps import bomb, corrupt, hostile_record, json_mcap, truncated


def test_a_file_is_told_by_its_magic_and_its_facts_read(tmp_path: Path) -> None:
    path = json_mcap(tmp_path / "a.mcap", 1000, topics=("/a", "/b"), metadata={"foxglove": {"deviceName": "r7"}})
    assert is_mcap(path.read_bytes()[:8]) and not is_mcap(b"RRF2" + bytes(4))
    facts = inspect(path)
    assert (facts.messages, facts.topics, facts.size) == (2000, ("/a", "/b"), path.stat().st_size)
    assert facts.named({"fleet": "robot_id", "foxglove": "deviceName"}) == "r7"
    assert facts.start_ns is not None and facts.end_ns is not None and facts.end_ns > facts.start_ns
    data = path.read_bytes()
    assert data[facts.data_end] == 0x0F  # the DataEnd record
    assert facts.head_digest == hashlib.sha256(data[:4096]).hexdigest()


def test_digests_at_offsets_are_those_of_the_prefixes(tmp_path: Path) -> None:
    path = json_mcap(tmp_path / "a.mcap", 300)
    data = path.read_bytes()
    with open(path, "rb") as f:
        found = digests_at(f, (10, 1000, len(data), len(data) + 5))
    assert found == {n: hashlib.sha256(data[:n]).hexdigest() for n in (10, 1000, len(data))}


@pytest.mark.parametrize(
    ("make", "why"),
    [
        (lambda src, dst: truncated(src, dst), "truncated"),
        (lambda src, dst: dst.write_bytes(MAGIC + b"\x00" * 10) and dst, "too short"),
        (lambda src, dst: dst.write_bytes(b"x" * 100 + src.read_bytes()[100:]) and dst, "does not begin"),
    ],
)
def test_a_file_that_is_not_a_whole_mcap_is_refused_naming_why(tmp_path: Path, make, why: str) -> None:  # type: ignore[no-untyped-def]
    bad = make(json_mcap(tmp_path / "a.mcap", 100), tmp_path / "bad.mcap")
    with pytest.raises(InvalidMcapError, match=why):
        inspect(bad)


def test_a_corrupt_chunk_is_found_by_its_crc_and_a_chunk_too_big_by_its_size(tmp_path: Path) -> None:
    good = json_mcap(tmp_path / "a.mcap", 2000)
    check_chunks(good, 1 << 20)
    bad = corrupt(good, tmp_path / "bad.mcap")
    assert inspect(bad).messages == 2000  # the structure and summary are intact
    with pytest.raises(InvalidMcapError, match="is corrupt"):
        check_chunks(bad, 1 << 20)
    with pytest.raises(ConversionLimitError, match="FLEET_MCAP_MEMORY_MB"):
        check_chunks(bomb(tmp_path / "bomb.mcap", 4 << 20), 1 << 20)
    with pytest.raises(InvalidMcapError, match="claims 2,147,483,648 bytes"):
        check_chunks(hostile_record(100, tmp_path / "claims.mcap"), 1 << 20)


def test_the_tail_holds_exactly_the_messages_after_a_held_copy(tmp_path: Path) -> None:
    short = json_mcap(tmp_path / "short.mcap", 40, chunk_size=1)
    long = json_mcap(tmp_path / "long.mcap", 100, chunk_size=1)
    held = inspect(short)
    assert long.read_bytes()[: held.data_end] == short.read_bytes()[: held.data_end]
    count = write_tail(long, held.data_end, inspect(long).data_end, tmp_path / "tail.mcap")
    with open(tmp_path / "tail.mcap", "rb") as f:
        sequences = [m.sequence for _, _, m in make_reader(f).iter_messages()]
    assert count == 60 and sequences == list(range(40, 100))
