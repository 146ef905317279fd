"""Reading a hot run's file: what comes out is what the decoder makes of the same bytes fed in small
pieces, whatever the reader's pieces, large messages among them, and wherever the size it was
given ends."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from services.hot.read import HotReader, read_events
from services.rrd.decoder import LARGE_MESSAGE, RrdDecoder
from tests.services.hot.page_cache import direct_reads_work, resident_bytes, uncache

RUN = """
import numpy as np, rerun as rr
rec = rr.RecordingStream("hot-read-test", recording_id="hot-read")
rec.save({path!r})
rng = np.random.default_rng(3)
for i in range(4):
    rec.set_time("frame", sequence=i)
    rec.log("/camera", rr.Image(rng.integers(0, 256, (360, 480, 3), dtype=np.uint8)))
    rec.log("/battery", rr.Scalars([float(i)]))
    rec.flush()
"""


@pytest.fixture(scope="module")
def run_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("hot-read") / "run.rrd"
    subprocess.run([sys.executable, "-c", RUN.format(path=str(path))], check=True, timeout=120)
    return path


def _fed(data: bytes, *, finish: bool = False) -> list[tuple[str, int, bytes]]:
    """The events of `data` fed to a decoder in small pieces (never the read-into path)."""
    decoder = RrdDecoder()
    events = [e for at in range(0, len(data), 4096) for e in decoder.feed(data[at : at + 4096])]
    return _plain(events + (list(decoder.finish()) if finish else []))


def _plain(events: list[Any]) -> list[tuple[str, int, bytes]]:
    return [(type(e).__name__, getattr(e, "offset", -1), bytes(getattr(e, "raw", b""))) for e in events]


def test_the_run_has_large_messages(run_file: Path) -> None:
    sizes = [len(e[2]) for e in _fed(run_file.read_bytes())]
    assert max(sizes) >= LARGE_MESSAGE  # the images: read by the decoder's large-message path


@pytest.mark.parametrize("limit", [64 * 1024, 1024 * 1024])
@pytest.mark.parametrize("cut", [1.0, 0.61, 0.3])
def test_a_hot_reader_gives_what_the_bytes_hold(run_file: Path, limit: int, cut: float) -> None:
    data = run_file.read_bytes()
    size = int(len(data) * cut)  # also mid-message: what a live run's reader may be given
    reader = HotReader(run_file)
    events: list[Any] = []
    try:
        while reader.position < size:
            before = reader.position
            events += reader.read(size, limit)
            assert reader.position - before <= limit
            if reader.position == before:
                break
    finally:
        reader.close()
    assert reader.position == size
    assert _plain(events) == _fed(data[:size])


def test_read_events_of_a_whole_run_match_the_bytes(run_file: Path) -> None:
    data = run_file.read_bytes()
    assert _plain(list(read_events(run_file, len(data)))) == _fed(data, finish=True)


def test_a_whole_run_is_read_around_the_page_cache(run_file: Path) -> None:
    """Sealing, hand-over and scrub read a run's file once, from the disk (its pages were dropped once
    written): read directly, it leaves the cache as it was, and costs the kernel no copy through it."""
    data = run_file.read_bytes()
    uncache(run_file)
    if not direct_reads_work(run_file) or resident_bytes(run_file) > len(data) // 2:
        pytest.skip(f"the file system under {run_file.parent} reads through the page cache whatever is asked")
    assert _plain(list(read_events(run_file, len(data)))) == _fed(data, finish=True)
    assert resident_bytes(run_file) < len(data) // 8, "the run was read through the page cache"
