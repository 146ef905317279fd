"""HotIndexTail: a growing hot run's entries read a piece at a time give what `read_hot_index` gives
for the whole file, each entry once, in file order; from the chunk index while it follows the file,
from the run file where it does not (missing, damaged, behind), never past the size it is given."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path
from typing import Any

import pytest

from services.hot.index import INDEX_FILE, MAGIC, HotEntry, index_records, read_hot_index, scan_run_file
from services.hot.store import HotRun, HotStore
from services.hot.tail import HotIndexTail
from services.rrd import iter_events
from services.rrd.chunk import chunk_meta
from services.rrd.frames import DEFAULT_VERSION, STREAM_HEADER_SIZE
from services.rrd.messages import ArrowMessage, BlueprintActivationMessage, Event, StoreInfoMessage, StoreKind
from tests.services.hot.indexing import append_recording, entry_keys, expected_entries
from tests.services.rrd.recordings import Recording
from tests.services.rrd.synthetic import write_recording

CHUNKS = 30


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    return write_recording(tmp_path / "rec.rrd", "rec-tail", CHUNKS)


def messages(path: Path) -> list[Event]:
    """The messages of a recording a hot run holds (what ingest appends)."""
    return [e for e in iter_events(path) if isinstance(e, ArrowMessage | StoreInfoMessage | BlueprintActivationMessage)]


def append(run: HotRun, event: Event) -> None:
    """Append one message as ingest does (a chunk with its metadata, so the index records it)."""
    if isinstance(event, ArrowMessage):
        run.append(event.kind, event.raw, event.store_id.kind, chunk_meta(event))
    elif isinstance(event, StoreInfoMessage):
        run.append(event.kind, event.raw, event.store_id.kind)
    elif isinstance(event, BlueprintActivationMessage):
        run.append(event.kind, event.raw, StoreKind.BLUEPRINT)


def whole(run: HotRun, size: int | None = None) -> list[HotEntry]:
    return read_hot_index(run.path, run.size if size is None else size).entries


def keys(entries: list[HotEntry]) -> list[tuple[str, int, int, bytes | None]]:
    """What a follower sends by: kind, offset, length and chunk id, in order."""
    return [(e.kind, e.offset, e.length, e.meta.chunk_id if e.meta else None) for e in entries]


def read_all(tail: HotIndexTail, size: int, limit: int = 4096) -> list[HotEntry]:
    """Read until a read returns nothing, checking each read keeps to `limit`."""
    entries: list[HotEntry] = []
    while batch := tail.read(size, limit):
        assert len(batch) <= limit
        entries += batch
    return entries


def full_run(hot_store: HotStore, recording: Path, run_id: str = "run-tail") -> HotRun:
    run = hot_store.create(run_id, DEFAULT_VERSION)
    assert append_recording(run, recording) > 0
    return run


def test_one_read_gives_what_the_whole_index_gives(hot_store: HotStore, recording: Path):
    run = full_run(hot_store, recording)
    expected = whole(run)
    assert len(expected) == CHUNKS + 2  # two SetStoreInfo (as the SDK sends), then every chunk
    tail = HotIndexTail(run.path)
    got = tail.read(run.size)
    assert entry_keys(got) == entry_keys(expected)  # rows and chunk metadata alike
    assert entry_keys(got) == entry_keys(expected_entries(run.path))  # and that is what the file says
    assert tail.position == run.size
    assert tail.read(run.size) == []  # nothing twice


def test_reads_while_the_file_grows_give_each_entry_once_in_order(hot_store: HotStore, recording: Path):
    run = hot_store.create("run-growing", DEFAULT_VERSION)
    tail = HotIndexTail(run.path)
    assert tail.read(run.size) == []  # only the stream header so far
    got: list[HotEntry] = []
    for i, event in enumerate(messages(recording)):
        append(run, event)
        if i % 3 == 1:  # sometimes several appends between reads, sometimes one
            continue
        got += tail.read(run.size)
        assert tail.position == run.size
        assert tail.read(run.size) == []
    got += tail.read(run.size)
    assert keys(got) == keys(whole(run))
    assert len({e.offset for e in got}) == len(got)


def test_limit_splits_the_entries_without_losing_or_repeating_one(hot_store: HotStore, recording: Path):
    run = full_run(hot_store, recording)
    tail = HotIndexTail(run.path)
    first = tail.read(run.size, limit=5)
    assert len(first) == 5 and tail.position == first[-1].end
    rest = read_all(tail, run.size, limit=5)
    assert keys(first + rest) == keys(whole(run))


def test_limit_holds_for_entries_read_from_the_run_file(hot_store: HotStore, recording: Path):
    run = full_run(hot_store, recording)
    (run.directory / INDEX_FILE).unlink()
    tail = HotIndexTail(run.path)
    got = read_all(tail, run.size, limit=4)
    assert keys(got) == keys(whole(run))


@pytest.mark.parametrize("index", [1, 7, CHUNKS + 1])
def test_a_follower_resuming_mid_file_skips_what_came_before(hot_store: HotStore, recording: Path, index: int):
    run = full_run(hot_store, recording)
    expected = whole(run)
    start = expected[index].offset
    tail = HotIndexTail(run.path, start)
    assert tail.position == start
    got = read_all(tail, run.size, limit=3)
    assert keys(got) == keys(expected[index:])
    assert tail.position == run.size


def test_resuming_mid_file_while_it_grows(hot_store: HotStore, recording: Path):
    run = hot_store.create("run-resume", DEFAULT_VERSION)
    events = messages(recording)
    for event in events[:10]:
        append(run, event)
    start = whole(run)[6].offset
    tail = HotIndexTail(run.path, start)
    got = tail.read(run.size)
    for event in events[10:]:
        append(run, event)
        got += tail.read(run.size)
    assert keys(got) == keys(whole(run)[6:])


def test_without_its_index_the_run_file_is_read(hot_store: HotStore, recording: Path):
    run = hot_store.create("run-no-index", DEFAULT_VERSION)
    events = messages(recording)
    half = len(events) // 2
    for event in events[:half]:
        append(run, event)
    (run.directory / INDEX_FILE).unlink()  # gone (the index writer still writes to the unlinked file)
    tail = HotIndexTail(run.path)
    got = tail.read(run.size)
    for event in events[half:]:
        append(run, event)
        got += tail.read(run.size)
    assert keys(got) == keys(expected_entries(run.path))
    assert entry_keys(got) == entry_keys(whole(run))  # chunk metadata read from the chunks themselves


def _record(payload: bytes) -> bytes:
    return struct.pack("<II", len(payload), zlib.crc32(payload)) + payload


def _records_end(index: Path, count: int) -> int:
    """Where the index file's `count`-th record ends."""
    return [end for end, _ in index_records(index.read_bytes())][count - 1]


def _bad_magic(index: Path) -> None:
    data = index.read_bytes()
    index.write_bytes(b"NOTANIDX" + data[len(MAGIC) :])


def _bad_crc(index: Path) -> None:
    data = bytearray(index.read_bytes())
    at = _records_end(index, 8) + 9  # a byte inside the ninth record's payload
    data[at] ^= 0xFF
    index.write_bytes(bytes(data))


def _unknown_record(index: Path) -> None:
    """A whole record (its CRC right) of a type no reader knows, after the eighth."""
    data = index.read_bytes()
    at = _records_end(index, 8)
    index.write_bytes(data[:at] + _record(b"Zgarbage") + data[at:])


def _unknown_layout(index: Path) -> None:
    """A chunk record naming a layout the file never defined."""
    data = index.read_bytes()
    records = list(index_records(data))
    at, (end, payload) = next((i, r) for i, r in enumerate(records) if r[1][:1] == b"C")
    bad = payload[:2] + struct.pack("<I", 999) + payload[6:]
    start = records[at - 1][0] if at else len(MAGIC)
    index.write_bytes(data[:start] + _record(bad) + data[end:])


def _cut_short(index: Path) -> None:
    data = index.read_bytes()
    index.write_bytes(data[: _records_end(index, 5) + 3])  # a record cut in its length field


@pytest.mark.parametrize("damage", [_bad_magic, _bad_crc, _unknown_record, _unknown_layout, _cut_short])
def test_a_damaged_index_falls_back_to_the_run_file(hot_store: HotStore, recording: Path, damage: Any):
    run = hot_store.create("run-damaged", DEFAULT_VERSION)
    events = messages(recording)
    for event in events[:20]:
        append(run, event)
    index = run.directory / INDEX_FILE
    run.index = None  # the writer stops: the damage stays as it is made
    damage(index)
    tail = HotIndexTail(run.path)
    got = tail.read(run.size, limit=6)
    for event in events[20:]:
        append(run, event)
        got += tail.read(run.size, limit=6)
    got += read_all(tail, run.size)
    assert keys(got) == keys(expected_entries(run.path))


def test_never_an_entry_past_the_size_it_is_given(hot_store: HotStore, recording: Path):
    run = full_run(hot_store, recording)
    expected = whole(run)
    tail = HotIndexTail(run.path)
    got: list[HotEntry] = []
    # sizes smaller than the file: at an entry's end, and inside an entry (a frame not yet whole)
    for size in (expected[3].end, expected[9].end - 1, expected[9].offset + 5, expected[15].end + 20):
        batch = tail.read(size)
        assert all(e.end <= size for e in batch)
        assert tail.position <= size
        got += batch
    assert keys(got) == keys([e for e in expected if e.end <= expected[15].end + 20])
    got += tail.read(run.size)
    assert keys(got) == keys(expected)


def test_never_past_the_size_when_reading_the_run_file(hot_store: HotStore, recording: Path):
    run = full_run(hot_store, recording)
    expected = whole(run)
    (run.directory / INDEX_FILE).unlink()
    tail = HotIndexTail(run.path)
    size = expected[10].end - 1  # the eleventh message is not whole within it
    batch = tail.read(size)
    assert keys(batch) == keys(expected[:10])
    assert tail.read(size) == []
    assert keys(tail.read(run.size)) == keys(expected[10:])


def test_an_index_behind_the_file_is_used_again_once_it_catches_up(
    hot_store: HotStore, recording: Path, monkeypatch: pytest.MonkeyPatch
):
    """A reader may see the run file grown before the record of its last message is written (ingest
    writes the message, then its record): that message comes from the run file, and the index is
    read again for what follows, not left for the rest of the run."""
    scanned: list[tuple[int, int]] = []

    def counting_scan(run_file: Path, start: int, size: int) -> list[HotEntry]:
        scanned.append((start, size))
        return scan_run_file(run_file, start, size)

    monkeypatch.setattr("services.hot.tail.scan_run_file", counting_scan)
    run = hot_store.create("run-lag", DEFAULT_VERSION)
    events = messages(recording)
    for event in events[:10]:
        append(run, event)
    index = run.directory / INDEX_FILE
    caught_up = index.read_bytes()
    index.write_bytes(caught_up[: _records_end(index, 8)])  # the last records not written yet
    tail = HotIndexTail(run.path)
    got = tail.read(run.size)
    assert scanned, "what the index lacks comes from the run file"
    index.write_bytes(caught_up)  # the writer caught up
    for event in events[10:]:
        append(run, event)
    scanned.clear()
    got += tail.read(run.size)
    assert keys(got) == keys(whole(run))
    assert scanned == [], "the index holds every message now: nothing is read from the run file"


def test_a_tail_of_a_fresh_run_starts_after_the_stream_header(hot_store: HotStore):
    run = hot_store.create("run-empty", DEFAULT_VERSION)
    tail = HotIndexTail(run.path)
    assert tail.position == STREAM_HEADER_SIZE == run.size
    assert tail.read(run.size) == []
    assert tail.read(run.size + 1000) == []  # a size past the file: nothing invented


@pytest.mark.sdk
@pytest.mark.parametrize("scene", ["points", "blueprint", "properties"])
def test_real_recordings_read_a_piece_at_a_time(hot_store: HotStore, recordings: dict[str, Recording], scene: str):
    run = hot_store.create(f"run-{scene}", DEFAULT_VERSION)
    tail = HotIndexTail(run.path)
    got: list[HotEntry] = []
    for event in messages(recordings[scene].path):
        append(run, event)
        got += tail.read(run.size, limit=2)
    got += read_all(tail, run.size)
    assert entry_keys(got) == entry_keys(whole(run))
