"""The hot run file and the page cache: once synced, only its tail stays cached."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from services.hot.store import CACHED_TAIL, HotRun
from services.rrd.frames import DEFAULT_VERSION, MessageKind

pytestmark = pytest.mark.skipif(shutil.which("fincore") is None, reason="needs util-linux's fincore")


def cached_bytes(path: Path) -> int:
    """How much of the file the page cache holds (util-linux `fincore`)."""
    out = subprocess.run(["fincore", "--bytes", "--noheadings", "--output", "RES", str(path)], capture_output=True)
    assert out.returncode == 0, out.stderr
    return int(out.stdout.split()[0])


def test_a_synced_run_file_keeps_only_its_tail_in_the_page_cache(tmp_path: Path):
    run = HotRun.create(tmp_path / "run-1", DEFAULT_VERSION)
    message = bytes(range(256)) * 4096  # 1 MiB
    for _ in range(5 * CACHED_TAIL // len(message)):
        run.append(MessageKind.ARROW_MSG, message)
    written = run.size
    assert cached_bytes(run.path) > written // 2  # just written: cached, so the check below can fail

    run.sync()

    assert written - CACHED_TAIL <= run.uncached <= written
    assert cached_bytes(run.path) <= CACHED_TAIL + (1 << 20)
    assert run.path.read_bytes()[-len(message) :] == message  # what was dropped from the cache is kept
    assert run.path.stat().st_size == written
    run.close()


def test_a_run_synced_often_with_little_written_each_time_asks_the_kernel_rarely(tmp_path: Path):
    run = HotRun.create(tmp_path / "run-1", DEFAULT_VERSION)
    steps = []
    for _ in range(3 * CACHED_TAIL // (256 << 10)):
        run.append(MessageKind.ARROW_MSG, bytes(256 << 10))
        run.sync()
        steps.append(run.uncached)
    assert len(set(steps)) <= 3  # a CACHED_TAIL at a time, not a drop per sync
    assert steps[-1] > 0
    run.close()
