"""The `lerobot` package in a virtualenv of its own (it pulls torch), created on demand and cached
outside the clone, for the test that loads the depot's LeRobot exports with the real loader.

    python -m tests.compat.lerobot_venv      create it if missing (CI does, beside its other installs)

It lives in ${XDG_CACHE_HOME:-~/.cache}/fleet-telemetry/tool-venvs/lerobot-0.4.4 (about 8 GB: torch's
CUDA build, which runs on the CPU; PyPI has no CPU-only build in lerobot's range) and is marked
complete only after the install and an import succeeded. 0.4.4 is the newest lerobot for Python
3.11; it reads and writes the v3.0 format, as every release since 0.4.0 does.
"""

from __future__ import annotations

from pathlib import Path

from tests.compat.tool_venvs import ToolVenv

NAME = "lerobot-0.4.4"
REQUIREMENTS = ["lerobot==0.4.4", "torch==2.10.0", "torchvision==0.25.0"]  # pinned: the resolver stays put
IMPORT = "from lerobot.datasets.lerobot_dataset import LeRobotDataset"


VENV = ToolVenv(NAME, tuple(REQUIREMENTS), IMPORT, timeout_s=1800)


def lerobot_python() -> Path:
    """The venv's python (created if missing)."""
    return VENV.python()


if __name__ == "__main__":
    print(lerobot_python())
