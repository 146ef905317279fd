"""Fixtures shared by every test package."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest


def find_rerun() -> str | None:
    """The `rerun` CLI installed next to this Python (the venv's), else the one on PATH."""
    candidate = Path(sys.executable).parent / "rerun"
    if candidate.is_file() and os.access(candidate, os.X_OK):
        return str(candidate)
    return shutil.which("rerun")


@pytest.fixture(scope="session", autouse=True)
def rerun_analytics_disabled() -> Iterator[None]:
    """Turn Rerun's analytics off once (tests must not talk to the network); failures are ignored."""
    exe = find_rerun()
    if exe is not None:
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            subprocess.run([exe, "analytics", "disable"], capture_output=True, timeout=60, check=False)
    yield


@pytest.fixture(scope="session")
def rerun_bin(rerun_analytics_disabled: None) -> str:
    """Path of the `rerun` executable (skips the test when it is not installed)."""
    exe = find_rerun()
    if exe is None:
        pytest.skip("the rerun CLI is not installed")
    return exe
