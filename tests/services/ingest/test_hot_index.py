"""Ingest keeps each hot run's chunk index as it files messages, readers get it through the
read-only `hot_recording` view, and it survives a restart and a process killed mid-write."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest

from services.hot.index import INDEX_FILE
from services.ingest.service import IngestService
from services.rrd import iter_events
from services.rrd.chunk_index import IndexRow
from services.rrd.frames import encode_message_header
from services.rrd.messages import ArrowMessage
from tests.services.hot.indexing import entry_keys, expected_entries
from tests.services.ingest import feeding
from tests.services.ingest.conftest import Factory
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk

ROOT = Path(__file__).resolve().parents[3]


def hot_index_of(service: IngestService, run_id: str) -> tuple[list[tuple[IndexRow, Any]], int, int]:
    recording = service.hot_recording(run_id)
    assert recording is not None
    index = recording.chunk_index()
    return entry_keys(index.entries), index.from_index, len(index.entries)


@pytest.mark.parametrize("scene", ["points", "optimized", "blueprint", "properties"])
def test_ingest_indexes_every_message_it_files(make_service: Factory, recordings: dict[str, Recording], scene: str):
    service = make_service()
    run_id = feeding.upload(service, iter_events(recordings[scene].path)).runs[0]
    keys, from_index, total = hot_index_of(service, run_id)
    assert from_index == total  # nothing had to be read from the run file
    assert keys == entry_keys(expected_entries(service.runs[run_id].hot.path))


def test_the_index_grows_with_the_run(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    events = list(iter_events(recordings["scalars"].path))
    source = service.open_source(live=True)
    half = len(events) // 2
    feeding.feed(service, source, events[:half])
    run_id = source.report.runs[0]
    seen_live, _, total_live = hot_index_of(service, run_id)
    feeding.feed(service, source, events[half:])
    seen, from_index, total = hot_index_of(service, run_id)
    service.close_source(source)
    assert 0 < total_live < total and seen[:total_live] == seen_live
    assert from_index == total
    assert seen == entry_keys(expected_entries(service.runs[run_id].hot.path))


def test_the_index_survives_a_restart(make_service: Factory, recordings: dict[str, Recording]):
    service = make_service()
    run_id = feeding.upload(service, iter_events(recordings["transforms"].path)).runs[0]
    before = hot_index_of(service, run_id)
    service.hot.close()
    restarted = make_service()
    assert restarted.recover() == [run_id]
    assert hot_index_of(restarted, run_id) == before


KILLED_WRITER = """
import datetime as dt, os, signal, sys
sys.path.insert(0, {root!r})
from pathlib import Path
from typing import Any
from services.hot import index
from services.rrd import iter_events
from tests.services.ingest import feeding
from tests.services.ingest.factory import ingest_service

writes = 0
real_write = index.HotIndexWriter._write

def write_then_die(self, records, covered):
    global writes
    writes += 1
    if writes == {die_at}:  # half of this record reaches the disk, then the process is killed
        data = b"".join(records)
        os.write(self._fd, data[: len(data) // 2])
        os.kill(os.getpid(), signal.SIGKILL)
    real_write(self, records, covered)

index.HotIndexWriter._write = write_then_die
service = ingest_service(Path({root_dir!r}), default_robot="r", max_streams=4)
feeding.upload(service, iter_events({path!r}))
"""


@pytest.mark.interpreted("services.hot.index")
def test_a_process_killed_mid_write_leaves_an_index_recovery_repairs(
    make_service: Factory, recordings: dict[str, Recording], tmp_path: Path
):
    rec = recordings["points"]
    chunks = sum(isinstance(e, ArrowMessage) for e in iter_events(rec.path))
    script = KILLED_WRITER.format(root=str(ROOT), die_at=chunks // 2, root_dir=str(tmp_path), path=str(rec.path))
    killed = subprocess.run([sys.executable, "-c", textwrap.dedent(script)], capture_output=True, timeout=120)
    assert killed.returncode == -signal.SIGKILL, killed.stderr.decode()
    (run_dir,) = (tmp_path / "hot").iterdir()
    with open(run_dir / "run.rrd", "ab") as fh:  # and the run file's last message was torn too
        fh.write(encode_message_header(2, 4000) + b"torn")
    service = make_service()
    (run_id,) = service.recover()
    keys, from_index, total = hot_index_of(service, run_id)
    hot_file = service.runs[run_id].hot.path
    assert from_index == total and keys == entry_keys(expected_entries(hot_file))
    # The rest of the recording (sent again, as a robot's upload would) is indexed on from there.
    feeding.upload(service, iter_events(rec.path))
    keys, from_index, total = hot_index_of(service, run_id)
    assert from_index == total and keys == entry_keys(expected_entries(hot_file))
    assert sum(key[0].kind == "chunk" for key in keys) == chunks
    assert (run_dir / INDEX_FILE).is_file()
