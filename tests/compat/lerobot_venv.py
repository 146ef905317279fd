"""The `lerobot` package in a virtualenv of its own (it pulls torch), created on demand and cached
outside the clone, for the test that loads the depot's LeRobot exports with the real loader.

    python -m tests.compat.lerobot_venv      create it if missing (CI does, beside its other installs)

It lives in ${XDG_CACHE_HOME:-~/.cache}/fleet-telemetry/tool-venvs/lerobot-0.4.4 (about 8 GB: torch's
CUDA build, which runs on the CPU; PyPI has no CPU-only build in lerobot's range) and is marked
complete only after the install and an import succeeded. 0.4.4 is the newest lerobot for Python
3.11; it reads and writes the v3.0 format, as every release since 0.4.0 does.
"""

from __future__ import annotations

import fcntl
import shutil
import subprocess
import sys
from pathlib import Path

from tests.compat.sdk_venvs import cache_root

READY_MARK = ".fleet-tool-ready"
NAME = "lerobot-0.4.4"
REQUIREMENTS = ["lerobot==0.4.4", "torch==2.10.0", "torchvision==0.25.0"]  # pinned: the resolver stays put
IMPORT = "from lerobot.datasets.lerobot_dataset import LeRobotDataset"


def venv_dir() -> Path:
    return cache_root().parent / "tool-venvs" / NAME


def lerobot_python() -> Path:
    """The venv's python (created if missing)."""
    root = venv_dir()
    if not (root / READY_MARK).exists():
        root.parent.mkdir(parents=True, exist_ok=True)
        with open(root.parent / f"{NAME}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)  # another worker or CI's step may be creating it
            if not (root / READY_MARK).exists():
                _create(root)
    return root / "bin" / "python"


def _create(root: Path) -> None:
    shutil.rmtree(root, ignore_errors=True)  # a creation that was interrupted
    _run([sys.executable, "-m", "venv", str(root)])
    python = str(root / "bin" / "python")
    _run([python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", *REQUIREMENTS])
    _run([python, "-c", IMPORT])
    (root / READY_MARK).write_text(" ".join(REQUIREMENTS) + "\n")


def _run(cmd: list[str]) -> None:
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stdout[-2000:]}{done.stderr[-2000:]}")


if __name__ == "__main__":
    print(lerobot_python())
