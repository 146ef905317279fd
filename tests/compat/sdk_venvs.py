"""One virtualenv per released rerun-sdk, created on demand and cached outside the clone.

    python -m tests.compat.sdk_venvs [X.Y.Z ...]    create (in parallel) what is missing; with no
                                                    version, every SDK the compatibility matrix uses

Each lives in ${XDG_CACHE_HOME:-~/.cache}/fleet-telemetry/sdk-venvs/X.Y.Z and is marked complete
only after `pip install rerun-sdk==X.Y.Z numpy` succeeded, so an interrupted creation is redone.
A file lock lets parallel test workers (or CI's pre-creation step) share one creation.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

READY_MARK = ".fleet-sdk-ready"

PINNED = "0.41.0"  # pyproject's dev extra: the matrix runs it from this project's venv
# The compatibility matrix: 0.23/0.24 send chunk store ids without application id, 0.25-0.27 write
# descriptors newer Rerun migrates, one 0.3x, and the pinned SDK. 0.22 is the one told to upgrade.
MATRIX = ["0.23.4", "0.24.1", "0.25.1", "0.26.2", "0.33.1", PINNED]
LEGACY = "0.22.1"


def cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "fleet-telemetry" / "sdk-venvs"


def venv_dir(version: str) -> Path:
    return cache_root() / version


def sdk_bin(version: str, name: str) -> Path:
    """`python` or `rerun` of the venv holding rerun-sdk==version (created if missing)."""
    ensure_venv(version)
    return venv_dir(version) / "bin" / name


def ensure_venv(version: str) -> Path:
    root = venv_dir(version)
    if (root / READY_MARK).exists():
        return root
    root.parent.mkdir(parents=True, exist_ok=True)
    with open(root.parent / f"{version}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another worker may be creating it: wait for it
        if (root / READY_MARK).exists():
            return root
        shutil.rmtree(root, ignore_errors=True)  # a creation that was interrupted
        _run([sys.executable, "-m", "venv", str(root)])
        _run(
            [
                str(root / "bin" / "python"),
                "-m",
                "pip",
                "install",
                "--quiet",
                "--disable-pip-version-check",
                f"rerun-sdk=={version}",
                "numpy",
            ]
        )
        # The SDK's CLI must not phone home from tests.
        subprocess.run(
            [str(root / "bin" / "rerun"), "analytics", "disable"], capture_output=True, timeout=120, check=False
        )
        (root / READY_MARK).write_text(version + "\n")
    return root


def _run(cmd: list[str]) -> None:
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=900, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stdout[-2000:]}{done.stderr[-2000:]}")


def main(versions: list[str]) -> None:
    versions = versions or [v for v in [*MATRIX, LEGACY] if v != PINNED]
    with ThreadPoolExecutor(max_workers=max(1, len(versions))) as pool:
        for root in pool.map(ensure_venv, versions):
            print(root)


if __name__ == "__main__":
    main(sys.argv[1:])
