"""The robot's spool: a recording's messages filed from a stream (an ingest source) or from a watched
file read in batches, one run file per recording, each chunk once; runs removed only once nothing
feeds them; everything found again after a restart."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from core.errors import InvalidArgumentError
from core.states import RunStatus
from services.agent.settings import load_agent_settings
from services.agent.spool import RUNS_DIR, Spool, store_infos
from services.hot.store import RUN_FILE
from services.ingest.view import HotRunView
from services.rrd import iter_events
from services.rrd.chunk import chunk_meta
from services.rrd.messages import ArrowMessage, Event, StoreInfoMessage, StreamStart
from tests.services.rrd.recordings import Recording
from tests.services.rrd.synthetic import recording_bytes, write_recording

CHUNKS = 15
MakeSpool = Callable[[], Spool]


@pytest.fixture
def make_spool(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[MakeSpool]:
    """Spools on one folder (a second one after closing the first: a restart of the agent)."""
    monkeypatch.delenv("FLEET_CONFIG", raising=False)
    made: list[Spool] = []

    def make() -> Spool:
        spool = Spool(load_agent_settings(agent_spool=tmp_path / "spool", agent_min_free_bytes=0))
        spool.recover()
        made.append(spool)
        return spool

    yield make
    for spool in made:
        spool.close()


@pytest.fixture
def spool(make_spool: MakeSpool) -> Spool:
    return make_spool()


@pytest.fixture
def recording(tmp_path: Path) -> Path:
    return write_recording(tmp_path / "robot.rrd", "run-spool", CHUNKS)


def chunk_ids(path: Path) -> Counter[bytes]:
    """How many times each chunk is in a file."""
    return Counter(chunk_meta(e).chunk_id for e in iter_events(path) if isinstance(e, ArrowMessage))


def status(run: HotRunView) -> RunStatus:
    return run.status


def run_file(spool: Spool, run_id: str) -> Path:
    return spool.root / RUNS_DIR / run_id / RUN_FILE


def stream(spool: Spool, events: list[Event], *, live: bool = True) -> None:
    source = spool.ingest.open_source(live=live)
    try:
        for event in events:
            spool.ingest.accept(source, event)
    finally:
        spool.ingest.close_source(source)


def test_a_stream_files_its_recording_into_one_run_each_chunk_once(spool: Spool, recording: Path):
    events = list(iter_events(recording))
    source = spool.ingest.open_source(live=True)
    for event in events:
        spool.ingest.accept(source, event)
    run = spool.run("run-spool")
    assert run is not None and spool.is_open(run) and status(run) == RunStatus.LIVE
    assert spool.remove("run-spool") is False  # a stream feeds it: never removed
    spool.ingest.close_source(source)
    run = spool.run("run-spool")  # as it is now
    assert run is not None and not spool.is_open(run) and status(run) == RunStatus.CLOSED
    assert [r.run_id for r in spool.runs()] == ["run-spool"]
    assert chunk_ids(run_file(spool, "run-spool")) == chunk_ids(recording)
    assert set(chunk_ids(recording).values()) == {1} and len(chunk_ids(recording)) == CHUNKS
    assert spool.size() == run.size == run_file(spool, "run-spool").stat().st_size
    recording_info = spool.recording("run-spool")
    assert recording_info is not None and recording_info.size == run.size

    stream(spool, events)  # the robot sends it again (its file copy): nothing is written twice
    assert chunk_ids(run_file(spool, "run-spool")) == chunk_ids(recording)
    assert spool.size() == run.size


def test_a_watched_file_is_filed_in_batches(spool: Spool, recording: Path):
    events = list(iter_events(recording))
    assert isinstance(events[0], StreamStart)
    batches = [events[:5], events[5:9], events[9:]]  # the first with the SetStoreInfo, the others without
    assert not any(isinstance(e, StoreInfoMessage) for e in batches[1] + batches[2])
    assert not spool.reading(recording)
    for batch in batches:
        assert spool.file_events(recording, batch) == ["run-spool"]
        assert spool.reading(recording)
        run = spool.run("run-spool")
        assert run is not None and spool.is_open(run)  # the file is still being read
    assert spool.remove("run-spool") is False
    spool.file_done(recording)
    assert not spool.reading(recording)
    run = spool.run("run-spool")
    assert run is not None and not spool.is_open(run)
    assert chunk_ids(run_file(spool, "run-spool")) == chunk_ids(recording)


def test_a_file_resumed_after_a_restart_passes_its_store_infos(make_spool: MakeSpool, recording: Path):
    events = list(iter_events(recording))
    first = make_spool()
    first.file_events(recording, events[:8])
    first.close()  # the agent stops mid-file (its progress saved after the eighth message)

    spool = make_spool()
    assert not spool.reading(recording)
    resumed = events[6:]  # a crash before the progress was saved: some messages come again
    assert not any(isinstance(e, StoreInfoMessage) for e in resumed)
    with pytest.raises(InvalidArgumentError, match="before its SetStoreInfo"):
        spool.file_events(Path("/elsewhere/other.rrd"), resumed)  # without its store infos: refused
    infos = store_infos(recording)
    assert len(infos) == 2 and all(isinstance(i, StoreInfoMessage) for i in infos)
    assert spool.file_events(recording, resumed[:4], infos) == ["run-spool"]
    assert spool.file_events(recording, resumed[4:]) == ["run-spool"]  # later batches need them no more
    spool.file_done(recording)
    assert chunk_ids(run_file(spool, "run-spool")) == chunk_ids(recording)  # each chunk once


def test_store_infos_of_a_torn_file_are_those_before_the_tear(tmp_path: Path):
    data = recording_bytes("run-torn", 6)
    torn = tmp_path / "torn.rrd"
    torn.write_bytes(data[: len(data) - 40])
    assert [i.store_id.recording_id for i in store_infos(torn)] == ["run-torn", "run-torn"]
    assert store_infos(tmp_path / "missing.rrd") == []


def test_remove_refuses_an_open_or_unknown_run_and_removes_a_closed_one(spool: Spool, tmp_path: Path):
    open_file = write_recording(tmp_path / "open.rrd", "run-open", 5)
    closed_file = write_recording(tmp_path / "closed.rrd", "run-closed", 5)
    spool.file_events(open_file, list(iter_events(open_file)))  # still read: open
    stream(spool, list(iter_events(closed_file)), live=False)  # an upload, done: closed
    assert spool.remove("run-nowhere") is False
    assert spool.remove("run-open") is False
    assert run_file(spool, "run-open").is_file()
    size_open = spool.run("run-open").size  # type: ignore[union-attr]
    assert spool.remove("run-closed") is True
    assert not (spool.root / RUNS_DIR / "run-closed").exists()
    assert spool.run("run-closed") is None and [r.run_id for r in spool.runs()] == ["run-open"]
    assert spool.size() == size_open
    assert spool.remove("run-closed") is False  # once


def test_recover_finds_every_run_after_a_restart(make_spool: MakeSpool, tmp_path: Path):
    first = make_spool()
    files = {run_id: write_recording(tmp_path / f"{run_id}.rrd", run_id, 6) for run_id in ("run-a", "run-b")}
    for path in files.values():
        stream(first, list(iter_events(path)))
    sizes = {run.run_id: run.size for run in first.runs()}
    first.close()

    spool = Spool(load_agent_settings(agent_spool=first.root, agent_min_free_bytes=0))
    try:
        assert sorted(spool.recover()) == ["run-a", "run-b"]
        assert {run.run_id: run.size for run in spool.runs()} == sizes
        assert all(not spool.is_open(run) and run.status == RunStatus.CLOSED for run in spool.runs())
        for run_id, path in files.items():
            assert chunk_ids(run_file(spool, run_id)) == chunk_ids(path)
            stream(spool, list(iter_events(path)))  # sent again: every chunk is known, none written
        assert {run.run_id: run.size for run in spool.runs()} == sizes
        assert spool.remove("run-a") is True  # a recovered, closed run may go
    finally:
        spool.close()


@pytest.mark.sdk
@pytest.mark.parametrize("scene", ["points", "blueprint", "properties"])
def test_a_real_recording_in_batches(spool: Spool, recordings: dict[str, Recording], scene: str):
    rec = recordings[scene]
    events = list(iter_events(rec.path))
    run_id = rec.recordings[0]["recording_id"]
    for start in range(0, len(events), 4):
        spool.file_events(rec.path, events[start : start + 4])
    spool.file_done(rec.path)
    assert chunk_ids(run_file(spool, run_id)) == chunk_ids(rec.path)


@pytest.mark.sdk
@pytest.mark.parametrize("scene", ["points", "blueprint"])
def test_a_real_recording_streamed_then_its_file_copy(spool: Spool, recordings: dict[str, Recording], scene: str):
    rec = recordings[scene]
    events = list(iter_events(rec.path))
    run_id = rec.recordings[0]["recording_id"]
    stream(spool, events)
    run = spool.run(run_id)
    assert run is not None and not spool.is_open(run)
    assert chunk_ids(run_file(spool, run_id)) == chunk_ids(rec.path)
    for start in range(0, len(events), 5):  # the robot's FileSink copy of it, watched: nothing new
        spool.file_events(rec.path, events[start : start + 5])
    spool.file_done(rec.path)
    after = spool.run(run_id)
    assert chunk_ids(run_file(spool, run_id)) == chunk_ids(rec.path) and after is not None and after.size == run.size
