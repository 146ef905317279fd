"""Virtualenvs of outside tools the tests use (LeRobot with torch, the MCAP writers), each created on
demand under ${XDG_CACHE_HOME:-~/.cache}/fleet-telemetry/tool-venvs/NAME, never in the project's
own venv. A venv is marked complete (READY_MARK) only after its install and an import succeeded,
and created under a file lock, so test workers and CI's install step may ask at once."""

from __future__ import annotations

import fcntl
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from tests.compat.sdk_venvs import cache_root

READY_MARK = ".fleet-tool-ready"


@dataclass(frozen=True)
class ToolVenv:
    name: str  # bump it when `requirements` change: a cache holding the old set is not the new one
    requirements: tuple[str, ...]  # pinned, so the resolver stays put
    import_check: str  # Python that must run in the venv once it is installed
    timeout_s: float = 900

    @property
    def root(self) -> Path:
        return cache_root().parent / "tool-venvs" / self.name

    def python(self) -> Path:
        """The venv's python (created if missing)."""
        root = self.root
        if not (root / READY_MARK).exists():
            root.parent.mkdir(parents=True, exist_ok=True)
            with open(root.parent / f"{self.name}.lock", "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)  # another worker or CI's step may be creating it
                if not (root / READY_MARK).exists():
                    self._create(root)
        return root / "bin" / "python"

    def _create(self, root: Path) -> None:
        shutil.rmtree(root, ignore_errors=True)  # a creation that was interrupted
        self._run([sys.executable, "-m", "venv", str(root)])
        python = str(root / "bin" / "python")
        self._run([python, "-m", "pip", "install", "--quiet", "--disable-pip-version-check", *self.requirements])
        self._run([python, "-c", self.import_check])
        (root / READY_MARK).write_text(" ".join(self.requirements) + "\n")

    def _run(self, cmd: list[str]) -> None:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=self.timeout_s, check=False)
        if done.returncode != 0:
            raise RuntimeError(
                f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stdout[-2000:]}{done.stderr[-2000:]}"
            )
