"""Importing FileSink recordings while they grow: FileTail and FileWatcher on real SDK files."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import random
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import pytest

from services.agent.files import FileProgress, FileTail, Phase, TailRead
from services.agent.watch import FileWatcher, is_recording_name
from services.rrd import iter_events
from services.rrd.errors import TruncatedError
from services.rrd.frames import FOOTER_ENTRY_SIZE, FOOTER_FIXED_SIZE, MESSAGE_HEADER_SIZE, STREAM_HEADER_SIZE
from services.rrd.messages import ArrowMessage, EndMessage, Event, StoreInfoMessage, StreamFooter, StreamStart
from tests.services.rrd.legacy import legacy_file
from tests.services.rrd.recordings import Recording, walk_frames

pytestmark = pytest.mark.sdk

SCENES = ("points", "scalars", "no_footer", "large", "blueprint")


@pytest.fixture(scope="module")
def files(recordings: dict[str, Recording]) -> dict[str, bytes]:
    """The bytes of real SDK recordings, plus files holding two streams one after the other."""
    data = {name: recordings[name].data for name in SCENES}
    data["concat"] = data["points"] + data["scalars"]  # End and footer, then a second stream
    data["concat_no_end"] = data["no_footer"] + data["points"]  # a stream without End, then another
    return data


def reference(data: bytes, tmp_path: Path) -> list[Event]:
    """What `iter_events` reads from the whole file."""
    path = tmp_path / "reference.rrd"
    path.write_bytes(data)
    return list(iter_events(path))


def event_end(event: Event) -> int:
    """The offset just past the bytes an event was decoded from."""
    if isinstance(event, StreamStart):
        return event.offset + STREAM_HEADER_SIZE
    if isinstance(event, StreamFooter):
        return event.offset + FOOTER_ENTRY_SIZE + FOOTER_FIXED_SIZE
    return event.offset + MESSAGE_HEADER_SIZE + len(event.raw)


def read_all(tail: FileTail, max_bytes: int = 1 << 20) -> tuple[list[Event], TailRead]:
    events: list[Event] = []
    while True:
        batch = tail.read(max_bytes)
        events += batch.events
        if not batch.more:
            return events, batch


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Collector:
    """The watcher's callbacks: what each file handed over, and a signal to wait on."""

    def __init__(self) -> None:
        self.batches: dict[Path, list[list[Event]]] = defaultdict(list)
        self.completed: dict[Path, list[FileProgress]] = defaultdict(list)
        self.saved: dict[str, FileProgress] = {}
        self.signal = asyncio.Event()

    async def on_events(self, path: Path, events: list[Event], progress: FileProgress) -> None:
        self.batches[path].append(events)
        self.saved[progress.path] = progress
        self.signal.set()

    async def on_complete(self, path: Path, progress: FileProgress) -> None:
        self.completed[path].append(progress)
        self.saved[progress.path] = progress
        self.signal.set()

    def events(self, path: Path) -> list[Event]:
        return [event for batch in self.batches[path] for event in batch]

    async def until(self, predicate: Callable[[], bool], timeout: float = 10.0) -> None:
        async with asyncio.timeout(timeout):
            while not predicate():
                self.signal.clear()
                if not predicate():
                    await self.signal.wait()


def cut_points(events: list[Event], size: int, seed: int) -> list[int]:
    """Sizes to grow a file through: inside stream headers, message headers and payloads, at
    every boundary, and at random bytes."""
    cuts = set(range(0, STREAM_HEADER_SIZE + 2))
    for event in events:
        for delta in (0, 1, 5, 13, 17):
            cuts.add(event.offset + delta)
        cuts.add(event_end(event) - 1)
        cuts.add(event_end(event) - 9)  # inside a footer's entry or its magic
    rng = random.Random(seed)
    cuts.update(rng.randrange(size) for _ in range(40))
    return [*sorted(c for c in cuts if 0 < c < size), size]


# --- FileTail ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["points", "blueprint", "large", "no_footer", "concat", "concat_no_end"])
def test_growing_file_yields_each_message_once_and_never_a_partial_one(
    files: dict[str, bytes], tmp_path: Path, name: str
) -> None:
    data = files[name]
    expected = reference(data, tmp_path)
    path = tmp_path / "growing.rrd"
    path.touch()
    tail = FileTail(path, clock=FakeClock())
    got: list[Event] = []
    written = 0
    with open(path, "ab") as fh:
        for cut in cut_points(expected, len(data), seed=len(data)):
            fh.write(data[written:cut])
            fh.flush()
            written = cut
            events, batch = read_all(tail, max_bytes=64 * 1024)
            assert all(event_end(e) <= written for e in events), "an event whose bytes are not all written"
            assert batch.progress.offset <= written
            got += events
    assert got == expected
    assert batch.progress.complete == (name != "no_footer")  # ended by End (no_footer waits to be idle)
    assert tail.read().events == []


def test_finished_file_completes_at_end_and_is_not_read_again(files: dict[str, bytes], tmp_path: Path) -> None:
    path = tmp_path / "points.rrd"
    path.write_bytes(files["points"])
    tail = FileTail(path, clock=FakeClock())
    events, batch = read_all(tail)
    assert events == reference(files["points"], tmp_path)
    assert batch.completed and batch.progress.complete
    assert batch.progress.offset == batch.progress.size == len(files["points"])
    assert batch.progress.phase is Phase.STREAM_HEADER and batch.progress.ended
    again = tail.read()
    assert again.events == [] and not again.completed and again.progress.complete


def test_batches_hold_about_max_bytes(files: dict[str, bytes], tmp_path: Path) -> None:
    path = tmp_path / "large.rrd"
    path.write_bytes(files["large"])
    tail = FileTail(path)
    limit = 1024 * 1024
    got, sizes = [], []
    while True:
        batch = tail.read(limit)
        got += batch.events
        messages = [
            len(e.raw) + MESSAGE_HEADER_SIZE for e in batch.events if not isinstance(e, StreamStart | StreamFooter)
        ]
        sizes.append((sum(messages), max(messages, default=0)))
        if not batch.more:
            break
    assert got == reference(files["large"], tmp_path)
    assert len(sizes) > 2
    assert all(total <= max(limit, biggest) for total, biggest in sizes)  # one message over the limit goes alone


def test_file_without_end_completes_when_idle(files: dict[str, bytes], tmp_path: Path) -> None:
    data = files["points"]
    frames, _ = walk_frames(data)
    torn = [f for f in frames if f.kind == 2][2]
    cut = torn.payload_offset + torn.length // 2  # an SDK killed while writing a chunk
    path = tmp_path / "cut.rrd"
    path.write_bytes(data[:cut])
    clock = FakeClock()
    tail = FileTail(path, idle_s=30, clock=clock)
    events, batch = read_all(tail)
    with pytest.raises(TruncatedError):
        list(iter_events(path))
    assert events == [e for e in reference(data, tmp_path) if e.offset < torn.offset]
    assert not batch.progress.complete and batch.progress.offset == torn.offset
    clock.now += 29
    assert not tail.read().completed
    clock.now += 1
    batch = tail.read()
    assert batch.completed and batch.events == [] and batch.progress.complete
    assert not tail.read().completed  # once
    with open(path, "ab") as fh:  # it grows after all: read on from the torn message
        fh.write(data[cut:])
    events, batch = read_all(tail)
    assert events == [e for e in reference(data, tmp_path) if e.offset >= torn.offset]
    assert batch.completed


def test_replaced_or_truncated_file_is_read_again_from_the_start(files: dict[str, bytes], tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    path.write_bytes(files["points"])
    tail = FileTail(path)
    read_all(tail)
    replacement = tmp_path / "new.rrd"
    replacement.write_bytes(files["scalars"])
    os.replace(replacement, path)  # a new inode
    events, batch = read_all(tail)
    assert batch.started_over and events == reference(files["scalars"], tmp_path)
    with open(path, "r+b") as fh:  # the same inode, shorter
        fh.truncate(0)
        fh.write(files["no_footer"])
    events, batch = read_all(tail)
    assert batch.started_over and events == reference(files["no_footer"], tmp_path)
    with open(path, "ab") as fh:  # growing is not replacing
        fh.write(files["points"])
    events, batch = read_all(tail)
    already = len(reference(files["no_footer"], tmp_path))  # (how many the SDK wrote: it batches as it likes)
    assert not batch.started_over and events == reference(files["concat_no_end"], tmp_path)[already:]
    with open(path, "r+b") as fh:  # the same inode, rewritten and larger by the next look
        fh.truncate(0)
        fh.write(files["blueprint"])
    events, batch = read_all(tail)
    assert batch.started_over and events == reference(files["blueprint"], tmp_path)
    stale = FileProgress(str(path), inode=path.stat().st_ino + 1, offset=100, size=200, phase=Phase.MESSAGES)
    events, batch = read_all(FileTail(path, stale))  # stored progress of an older file there
    assert batch.started_over and events == reference(files["blueprint"], tmp_path)


def damage_kind(data: bytes) -> tuple[bytes, int]:
    frames, _ = walk_frames(data)
    at = frames[3].offset
    return data[:at] + (9).to_bytes(8, "little") + data[at + 8 :], at


def damage_protobuf(data: bytes) -> tuple[bytes, int]:
    frames, _ = walk_frames(data)
    store_info = frames[0]
    assert store_info.kind == 1
    start = store_info.payload_offset
    return data[:start] + b"\xff" * store_info.length + data[start + store_info.length :], store_info.offset


@pytest.mark.parametrize("damage", [damage_kind, damage_protobuf])
def test_damaged_message_stops_the_tail_with_one_warning(
    files: dict[str, bytes], tmp_path: Path, caplog: pytest.LogCaptureFixture, damage: Callable[..., tuple[bytes, int]]
) -> None:
    data, at = damage(files["points"])
    path = tmp_path / "damaged.rrd"
    path.write_bytes(data)
    tail = FileTail(path)
    with caplog.at_level(logging.WARNING, logger="services.agent.files"):
        events, batch = read_all(tail)
        for _ in range(3):
            assert tail.read().events == []
        with open(path, "ab") as fh:
            fh.write(files["points"])
        assert tail.read().events == []
        FileTail(path, batch.progress).read()  # restarted from the stored progress: still stopped
    assert events == [e for e in reference(files["points"], tmp_path) if e.offset < at]
    assert batch.progress.damaged_at == at and str(at) in batch.progress.damage
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1, warnings
    assert str(path) in warnings[0] and f"byte {at}" in warnings[0]


@pytest.mark.parametrize("stop_after", ["mid_message", "after_end", "second_stream"])
def test_tail_resumes_from_stored_progress(files: dict[str, bytes], tmp_path: Path, stop_after: str) -> None:
    data = files["concat"]
    expected = reference(data, tmp_path)
    end = next(e for e in expected if isinstance(e, EndMessage))
    cut = {
        "mid_message": expected[4].offset + 20,
        "after_end": event_end(end),  # the footer is not written yet
        "second_stream": len(files["points"]) + STREAM_HEADER_SIZE + 30,
    }[stop_after]
    path = tmp_path / "resumed.rrd"
    path.write_bytes(data[:cut])
    first, batch = read_all(FileTail(path))
    stored = json.loads(json.dumps(batch.progress.to_dict()))
    with open(path, "ab") as fh:
        fh.write(data[cut:])
    rest, batch = read_all(FileTail(path, FileProgress.from_dict(stored)))
    assert first + rest == expected
    assert rest and rest[0].offset == stored["offset"] and batch.progress.complete


def test_resumed_tail_completes_store_ids_of_streams_before_0_25(files: dict[str, bytes], tmp_path: Path) -> None:
    source = tmp_path / "points.rrd"
    source.write_bytes(files["points"])
    legacy = legacy_file(source, tmp_path / "legacy.rrd")
    expected = list(iter_events(legacy))
    assert all(e.store_id.application_id == "fleet_points" for e in expected if isinstance(e, ArrowMessage))
    data = legacy.read_bytes()
    path = tmp_path / "growing.rrd"
    path.write_bytes(data[: expected[5].offset])
    first, batch = read_all(FileTail(path))
    with open(path, "ab") as fh:
        fh.write(data[expected[5].offset :])
    rest, _ = read_all(FileTail(path, batch.progress))
    assert not any(isinstance(e, StoreInfoMessage) for e in rest)
    assert first + rest == expected


def test_progress_round_trips_and_refuses_bad_input() -> None:
    progress = FileProgress("/data/a.rrd", 7, 120, 300, 5, False, Phase.FOOTER, 0, 0, 104, 16, 99, None, "")
    assert FileProgress.from_dict(json.loads(json.dumps(progress.to_dict()))) == progress
    assert FileProgress.from_dict({"path": "/x.rrd", "future_field": 1}) == FileProgress("/x.rrd")
    for bad, named in (
        ({}, "'path'"),
        ({"path": "/x", "offset": "12"}, "'offset'"),
        ({"path": "/x", "phase": "x"}, "'phase'"),
    ):
        with pytest.raises(ValueError, match=named):
            FileProgress.from_dict(bad)


def test_recording_names() -> None:
    assert is_recording_name("run-1.rrd")
    for name in (".run.rrd", "~run.rrd", "#run.rrd", "run.rrd.tmp", "run.rrd~", ".rrd", "run.txt"):
        assert not is_recording_name(name), name


# --- FileWatcher ---------------------------------------------------------------------------


def watcher(dirs: list[Path], got: Collector, **kwargs: object) -> FileWatcher:
    return FileWatcher(dirs, got.on_events, got.on_complete, **kwargs)  # type: ignore[arg-type]


def test_watcher_imports_finished_files_once(files: dict[str, bytes], tmp_path: Path) -> None:
    (tmp_path / "sub").mkdir()
    (tmp_path / ".hidden").mkdir()
    names = {"points.rrd": "points", "sub/blueprint.rrd": "blueprint", "sub/two.rrd": "concat"}
    for name, scene in names.items():
        (tmp_path / name).write_bytes(files[scene])
    for ignored in (".hidden/x.rrd", ".points.rrd", "notes.txt", "points.rrd.tmp"):
        (tmp_path / ignored).write_bytes(files["points"])
    got = Collector()

    async def scenario() -> FileWatcher:
        w = watcher([tmp_path], got, notify=False, batch_bytes=8192)
        await w.scan()
        calls = sum(len(b) for b in got.batches.values())
        await w.scan()
        assert sum(len(b) for b in got.batches.values()) == calls  # nothing new, nothing read
        return w

    w = asyncio.run(scenario())
    assert set(got.batches) == {tmp_path / name for name in names}
    for name, scene in names.items():
        assert got.events(tmp_path / name) == reference(files[scene], tmp_path)
        [done] = got.completed[tmp_path / name]
        assert done.complete and done.offset == len(files[scene])
    assert {Path(p) for p in w.progress()} == {tmp_path / name for name in names}


def test_restarted_watcher_reads_only_what_was_appended(files: dict[str, bytes], tmp_path: Path) -> None:
    data = files["blueprint"]
    expected = reference(data, tmp_path)
    watched = tmp_path / "watched"
    watched.mkdir()
    path = watched / "run.rrd"
    cut = expected[7].offset + 3
    path.write_bytes(data[:cut])
    before, after = Collector(), Collector()
    asyncio.run(watcher([watched], before, notify=False).scan())
    stored = [json.dumps(p.to_dict()) for p in before.saved.values()]  # as the agent's store keeps them
    with open(path, "ab") as fh:
        fh.write(data[cut:])
    progress = [FileProgress.from_dict(json.loads(s)) for s in stored]
    asyncio.run(watcher([watched], after, notify=False, progress=progress).scan())
    assert before.events(path) + after.events(path) == expected
    assert after.events(path)[0].offset == expected[7].offset
    assert not before.completed and len(after.completed[path]) == 1


def test_events_are_read_again_when_filing_them_fails(files: dict[str, bytes], tmp_path: Path) -> None:
    (tmp_path / "a.rrd").write_bytes(files["points"])
    got = Collector()
    failures = [RuntimeError("spool full")]
    threads = set()
    real_read = FileTail.read

    def read(self: FileTail, max_bytes: int = 0) -> TailRead:
        threads.add(threading.get_ident())
        return real_read(self, max_bytes)

    async def on_events(path: Path, events: list[Event], progress: FileProgress) -> None:
        if failures:
            raise failures.pop()
        await got.on_events(path, events, progress)

    async def scenario() -> None:
        w = FileWatcher([tmp_path], on_events, got.on_complete, notify=False)
        await w.scan()
        assert not got.batches and not got.completed
        await w.scan()

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(FileTail, "read", read)
        asyncio.run(scenario())
    assert got.events(tmp_path / "a.rrd") == reference(files["points"], tmp_path)
    assert threading.get_ident() not in threads  # files are read off the event loop's thread


async def stop_quickly(w: FileWatcher) -> None:
    t0 = time.monotonic()
    await w.stop()
    assert time.monotonic() - t0 < 2


def test_watcher_notices_new_files_and_directories_promptly(files: dict[str, bytes], tmp_path: Path) -> None:
    got = Collector()

    async def scenario() -> None:
        w = watcher([tmp_path], got, rescan_s=120)  # the rescan would come too late: notification finds them
        w.start()
        await asyncio.wait_for(w.scanned.wait(), 10)
        (tmp_path / "new.rrd").write_bytes(files["points"])
        await got.until(lambda: bool(got.completed[tmp_path / "new.rrd"]))
        (tmp_path / "later" / "deeper").mkdir(parents=True)
        (tmp_path / "later" / "deeper" / "run.rrd").write_bytes(files["scalars"])
        await got.until(lambda: bool(got.completed[tmp_path / "later" / "deeper" / "run.rrd"]))
        with open(tmp_path / "new.rrd", "ab") as fh:  # a second stream appended: read on
            fh.write(files["scalars"])
        await got.until(lambda: len(got.completed[tmp_path / "new.rrd"]) == 2)
        await stop_quickly(w)

    asyncio.run(scenario())
    assert got.events(tmp_path / "new.rrd") == reference(files["concat"], tmp_path)
    assert got.events(tmp_path / "later" / "deeper" / "run.rrd") == reference(files["scalars"], tmp_path)


def test_watcher_waits_for_a_missing_directory_and_completes_idle_files(
    files: dict[str, bytes], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    missing = tmp_path / "mnt" / "robot"
    got = Collector()
    data = files["no_footer"]  # no End: complete only once idle

    async def scenario() -> None:
        w = watcher([missing], got, rescan_s=0.2, idle_s=0.5)
        w.start()
        await asyncio.wait_for(w.scanned.wait(), 10)
        await asyncio.sleep(0.5)  # a few rescans find it still missing: one warning, not one each
        missing.mkdir(parents=True)
        (missing / "run.rrd").write_bytes(data)
        await got.until(lambda: bool(got.completed[missing / "run.rrd"]))
        await stop_quickly(w)

    with caplog.at_level(logging.WARNING, logger="services.agent.files"):
        asyncio.run(scenario())
    assert got.events(missing / "run.rrd") == reference(data, tmp_path)
    [warning] = [r.getMessage() for r in caplog.records]
    assert str(missing) in warning and "does not exist" in warning


LIVE_SCRIPT = """
import sys, time
import rerun as rr
rec = rr.RecordingStream("fleet_live", recording_id="rec-live")
rec.set_sinks(rr.FileSink(sys.argv[1]))
deadline = time.monotonic() + float(sys.argv[2])
i = 0
while time.monotonic() < deadline:
    rec.set_time("step", sequence=i)
    rec.log("/robot/speed", rr.Scalars([float(i)]))
    rec.log("/world/points", rr.Points3D([[i, 0.0, 0.0]] * 50))
    if i % 10 == 0:
        rec.flush()
    i += 1
    time.sleep(0.01)
rec.flush()
rec.disconnect()
"""


def test_watcher_tails_a_live_sdk_process(tmp_path: Path) -> None:
    got = Collector()
    path = tmp_path / "live.rrd"

    async def scenario() -> None:
        w = watcher([tmp_path], got, rescan_s=1, idle_s=30, batch_bytes=16 * 1024)
        w.start()
        await asyncio.wait_for(w.scanned.wait(), 10)
        proc = subprocess.Popen([sys.executable, "-c", LIVE_SCRIPT, str(path), "3"], stderr=subprocess.PIPE)
        try:
            await got.until(lambda: len(got.batches[path]) >= 2, timeout=20)
            assert proc.poll() is None, "read while being written"
            _, err = await asyncio.to_thread(proc.communicate, timeout=60)
            assert proc.returncode == 0, err.decode()
        finally:
            proc.kill()
        await got.until(lambda: bool(got.completed[path]), timeout=15)
        await stop_quickly(w)

    asyncio.run(scenario())
    expected = list(iter_events(path))
    assert got.events(path) == expected
    assert isinstance(expected[-1], StreamFooter) and len(got.batches[path]) > 2
    [done] = got.completed[path]
    assert done.offset == path.stat().st_size
