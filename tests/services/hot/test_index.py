"""The chunk index beside a hot run file: kept as messages are appended, read back as what the file
says (rows, chunk metadata, the footer manifest built from them), and after a crash trimmed or
rebuilt to match what the run file still holds."""

from __future__ import annotations

import os
import struct
import tracemalloc
import zlib
from pathlib import Path

import pytest

from services.hot.index import INDEX_FILE, MAGIC, HotIndexWriter, read_hot_index
from services.hot.store import HotRun, HotStore
from services.rrd import iter_events
from services.rrd.chunk import ChunkMeta, chunk_meta
from services.rrd.frames import DEFAULT_VERSION, MessageKind
from services.rrd.messages import ArrowMessage, StoreId, StoreKind
from tests.services.hot.indexing import append_recording, entry_keys, expected_entries, manifest_of
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk  # the recordings are written by the real SDK

# Scenes with chunks of every kind the index describes: sparse components (nulls), static data,
# properties, several timelines of each type, a blueprint store with its activation, 1 MB chunks.
SCENES = (
    "points",
    "scalars",
    "textlogs",
    "transforms",
    "static",
    "properties",
    "blueprint",
    "large",
    "image",
    "optimized",  # `rerun rrd optimize` merges chunks: components with nulls, ranges of their own
    "merged",
)


def recording_store(rec: Recording) -> StoreId:
    first = rec.recordings[0]
    return StoreId(StoreKind.RECORDING, first["application_id"], first["recording_id"])


def reopened(hot_store: HotStore, run: HotRun) -> HotRun:
    """The run after a restart (its file closed, then recovered from disk)."""
    hot_store.forget(run)
    recovered = hot_store.recover(run.directory)
    return recovered


@pytest.mark.parametrize("scene", SCENES)
def test_the_index_says_what_the_file_says(hot_store: HotStore, recordings: dict[str, Recording], scene: str):
    rec = recordings[scene]
    run = hot_store.create(f"run-{scene}", DEFAULT_VERSION)
    append_recording(run, rec.path)
    index = read_hot_index(run.path, run.size)
    expected = expected_entries(run.path)
    assert index.from_index == len(index.entries) == len(expected)  # all of it from the index file
    assert entry_keys(index.entries) == entry_keys(expected)
    table, sorbet, sha = manifest_of(index.entries, recording_store(rec))
    want_table, want_sorbet, want_sha = manifest_of(expected, recording_store(rec))
    assert table.equals(want_table) and table.schema.equals(want_table.schema, check_metadata=True)
    assert sorbet.equals(want_sorbet, check_metadata=True) and sha == want_sha


def test_readers_take_what_the_index_lacks_from_the_file(hot_store: HotStore, recordings: dict[str, Recording]):
    rec = recordings["scalars"]
    run = hot_store.create("run-lagging", DEFAULT_VERSION)
    appended = append_recording(run, rec.path, limit=6)
    append_recording_rest(run, rec, skip=appended)  # chunks without metadata: the index stops
    assert run.index is not None and run.index.stopped
    index = read_hot_index(run.path, run.size)
    assert 0 < index.from_index < len(index.entries)
    assert entry_keys(index.entries) == entry_keys(expected_entries(run.path))


def append_recording_rest(run: HotRun, rec: Recording, skip: int) -> None:
    from services.rrd import iter_events
    from services.rrd.messages import ArrowMessage, StoreInfoMessage

    events = [e for e in iter_events(rec.path) if isinstance(e, ArrowMessage | StoreInfoMessage)][skip:]
    for event in events:
        run.append(event.kind, event.raw, event.store_id.kind)


def test_a_reader_sees_only_the_size_it_was_given(hot_store: HotStore, recordings: dict[str, Recording]):
    rec = recordings["points"]
    run = hot_store.create("run-growing", DEFAULT_VERSION)
    append_recording(run, rec.path, limit=5)
    size = run.size
    append_recording_rest_with_meta(run, rec, skip=5)
    index = read_hot_index(run.path, size)
    assert index.entries and all(e.row.end <= size for e in index.entries)
    assert index.entries[-1].row.end == size
    assert entry_keys(index.entries) == entry_keys([e for e in expected_entries(run.path) if e.row.end <= size])


def append_recording_rest_with_meta(run: HotRun, rec: Recording, skip: int) -> None:
    from services.rrd import iter_events
    from services.rrd.chunk import chunk_meta
    from services.rrd.messages import ArrowMessage

    events = [e for e in iter_events(rec.path) if isinstance(e, ArrowMessage)][skip:]
    for event in events:
        run.append(event.kind, event.raw, event.store_id.kind, chunk_meta(event))


def test_a_restart_keeps_the_index(hot_store: HotStore, recordings: dict[str, Recording]):
    rec = recordings["transforms"]
    run = hot_store.create("run-restart", DEFAULT_VERSION)
    append_recording(run, rec.path)
    before = (run.directory / INDEX_FILE).read_bytes()
    run = reopened(hot_store, run)
    assert (run.directory / INDEX_FILE).read_bytes() == before  # nothing to redo
    append_recording(run, recordings["points"].path, limit=4)  # and it grows on after the restart
    index = read_hot_index(run.path, run.size)
    assert index.from_index == len(index.entries)
    assert entry_keys(index.entries) == entry_keys(expected_entries(run.path))


def test_a_torn_tail_is_trimmed_from_the_file_and_its_index(hot_store: HotStore, recordings: dict[str, Recording]):
    rec = recordings["large"]  # 1 MB chunks: a crash in the middle of writing one
    run = hot_store.create("run-torn", DEFAULT_VERSION)
    append_recording(run, rec.path)
    whole = expected_entries(run.path)
    last = whole[-1].row
    assert last.kind == "chunk"
    index_before = (run.directory / INDEX_FILE).read_bytes()
    hot_store.forget(run)
    # The crash: the last chunk was only half written, though its index record made it to disk.
    os.truncate(run.path, last.offset + last.length // 2)
    recovered = hot_store.recover(run.directory)
    assert recovered.size == last.offset
    assert len((run.directory / INDEX_FILE).read_bytes()) < len(index_before)
    index = read_hot_index(recovered.path, recovered.size)
    assert index.from_index == len(index.entries) == len(whole) - 1
    assert entry_keys(index.entries) == entry_keys(whole[:-1])


def test_an_index_behind_its_file_is_completed(hot_store: HotStore, recordings: dict[str, Recording]):
    rec = recordings["scalars"]
    run = hot_store.create("run-behind", DEFAULT_VERSION)
    append_recording(run, rec.path)
    path = run.directory / INDEX_FILE
    data = path.read_bytes()
    hot_store.forget(run)
    path.write_bytes(data[: len(data) // 2])  # a crash (or a lost page) took its second half
    recovered = hot_store.recover(run.directory)
    index = read_hot_index(recovered.path, recovered.size)
    assert index.from_index == len(index.entries)
    assert entry_keys(index.entries) == entry_keys(expected_entries(recovered.path))


@pytest.mark.parametrize("damage", ["missing", "foreign", "flipped", "zeroed"])
def test_a_missing_or_damaged_index_is_rebuilt(hot_store: HotStore, recordings: dict[str, Recording], damage: str):
    rec = recordings["textlogs"]
    run = hot_store.create(f"run-{damage}", DEFAULT_VERSION)
    append_recording(run, rec.path)
    path = run.directory / INDEX_FILE
    data = bytearray(path.read_bytes())
    hot_store.forget(run)
    if damage == "missing":
        path.unlink()
    elif damage == "foreign":
        path.write_bytes(b"not an index at all")
    elif damage == "flipped":
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    else:  # a power loss can leave a run of zeros where data was
        data[len(MAGIC) + 40 : len(MAGIC) + 400] = bytes(360)
        path.write_bytes(bytes(data))
    expected = entry_keys(expected_entries(run.path))
    # Before recovery, a reader still gets the whole truth (from the file where the index fails).
    assert entry_keys(read_hot_index(run.path, run.size).entries) == expected
    recovered = hot_store.recover(run.directory)
    index = read_hot_index(recovered.path, recovered.size)
    assert index.from_index == len(index.entries)
    assert entry_keys(index.entries) == expected


def test_a_failed_index_write_stops_the_index_not_the_run(
    hot_store: HotStore, recordings: dict[str, Recording], monkeypatch: pytest.MonkeyPatch
):
    rec = recordings["points"]
    run = hot_store.create("run-disk-full", DEFAULT_VERSION)
    append_recording(run, rec.path, limit=4)
    assert run.index is not None
    length = (run.directory / INDEX_FILE).stat().st_size
    real_write = os.write

    def full_disk(fd: int, data: bytes) -> int:
        if fd == run.index._fd:  # type: ignore[union-attr]
            real_write(fd, data[: len(data) // 2])  # half of it made it to disk
            raise OSError(28, "No space left on device")
        return real_write(fd, data)

    monkeypatch.setattr(os, "write", full_disk)
    append_recording_rest_with_meta(run, rec, skip=3)  # the run file takes every chunk
    monkeypatch.undo()
    assert run.index.stopped
    assert (run.directory / INDEX_FILE).stat().st_size == length  # no half record left
    index = read_hot_index(run.path, run.size)
    assert entry_keys(index.entries) == entry_keys(expected_entries(run.path))
    recovered = reopened(hot_store, run)
    assert read_hot_index(recovered.path, recovered.size).from_index == len(index.entries)


def test_a_message_appended_without_index_details(hot_store: HotStore):
    run = hot_store.create("run-bare", DEFAULT_VERSION)
    run.append(MessageKind.ARROW_MSG, b"x" * 100)  # a chunk whose metadata nobody gave
    assert run.index is not None and run.index.stopped
    assert run.size > 12


def _documented_record(meta: ChunkMeta, store_kind: int, layout_id: int, offset: int, length: int) -> bytes:
    """A chunk's record as the format in services/hot/index.py describes it, built field by field."""
    names = [ix.name for ix in meta.layout.indexes]
    out = struct.pack("<cBIqqqq", b"C", store_kind, layout_id, offset, length, meta.num_rows, meta.uncompressed_size)
    out += meta.chunk_id + struct.pack("<H", len(meta.timelines))
    full = {t.name: t.range for t in meta.timelines}
    for t in meta.timelines:
        out += struct.pack("<Hqq", names.index(t.name), t.range.min, t.range.max)
    for c in meta.components:
        if c.num_rows == meta.num_rows and c.ranges == full:
            out += b"\0"
        else:
            out += struct.pack("<BqH", 1, c.num_rows, len(c.ranges))
            for name, r in c.ranges.items():
                out += struct.pack("<Hqq", names.index(name), r.min, r.max)
    return struct.pack("<II", len(out), zlib.crc32(out)) + out


@pytest.mark.parametrize("scene", ["scalars", "optimized", "points"])
def test_chunk_records_are_the_documented_bytes(tmp_path: Path, recordings: dict[str, Recording], scene: str):
    """The common record is packed in one go (every timeline, every component in every row); it and
    the explicit one are the bytes the format describes."""
    writer = HotIndexWriter.create(tmp_path)
    layouts: dict[int, int] = {}
    explicit = 0
    for event in iter_events(recordings[scene].path):
        if not isinstance(event, ArrowMessage):
            continue
        meta = chunk_meta(event)
        records = writer._chunk_records(event.store_id.kind, event.offset, 100, meta)
        layout_id = layouts.setdefault(id(meta.layout), len(layouts))
        assert records[-1] == _documented_record(meta, event.store_id.kind, layout_id, event.offset, 100)
        explicit += any(c.num_rows != meta.num_rows for c in meta.components)
    writer.close()
    if scene == "optimized":
        assert explicit, "no record with a component of its own: the explicit form went untested"


def test_recovering_a_run_holds_a_few_of_its_messages_not_all(hot_store: HotStore, recordings: dict[str, Recording]):
    """A restart with a big run still hot reads its file as it streams: the run's size in memory
    would be 1.2 GB for a 1 GB run, and more than the machine has for a 50 GB one."""
    run = hot_store.create("run-big", DEFAULT_VERSION)
    while run.size < 24 << 20:
        append_recording(run, recordings["large"].path)
    index_file = run.directory / INDEX_FILE
    index_before = index_file.read_bytes()
    hot_store.forget(run)
    # Half the index lost too, so that recovery also indexes what the rest of the file holds.
    index_file.write_bytes(index_before[: len(index_before) // 2])
    tracemalloc.start()
    try:
        recovered = hot_store.recover(run.directory)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert recovered.size == run.size
    assert peak < run.size // 3, f"recovering a {run.size}-byte run took {peak} bytes"
    index = read_hot_index(recovered.path, recovered.size)
    assert index.from_index == len(index.entries)  # the half it lacked indexed again
    assert entry_keys(index.entries) == entry_keys(expected_entries(recovered.path))
