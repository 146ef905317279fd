"""What of a file the page cache holds, and whether its file system reads around the cache: asked of
the system itself, for tests of readers that should leave the cache alone."""

from __future__ import annotations

import mmap
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from services.hot.direct import ALIGN


def resident_bytes(path: Path) -> int:
    fincore = shutil.which("fincore")  # util-linux
    if fincore is None:
        pytest.skip("fincore (util-linux) tells what of a file the page cache holds")
    answer = subprocess.run(
        [fincore, "--bytes", "--noheadings", "--output", "RES", str(path)], capture_output=True, text=True, check=True
    )
    return int(answer.stdout.strip())


def uncache(path: Path) -> None:
    """Evict a file's pages from the page cache (written back first): its next reader reads the disk,
    as a hot run's file is read when it is promoted (the depot drops a run's pages once on disk)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)


def direct_reads_work(path: Path) -> bool:
    """Asked of the file system itself, not of the code under test."""
    if not hasattr(os, "O_DIRECT"):
        return False
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECT)
    except OSError:
        return False
    try:
        with mmap.mmap(-1, ALIGN) as buffer:
            os.preadv(fd, [buffer], 0)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)
