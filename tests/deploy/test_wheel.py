"""The wheel pip builds from the repository (what the image installs, deploy/Dockerfile) holds every
file of the packages: a template or an asset left out of it fails only once deployed."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def tracked_package_files() -> list[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = [p.rstrip("*") for p in project["tool"]["setuptools"]["packages"]["find"]["include"]]
    listed = subprocess.run(["git", "ls-files", *packages], cwd=ROOT, capture_output=True, text=True, check=True)
    return [name for name in listed.stdout.splitlines() if not name.endswith("/.gitignore")]


@pytest.mark.slow
def test_the_wheel_holds_every_file_of_the_packages(tmp_path: Path):
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: the package's files are what git tracks")
    source, wheels = tmp_path / "src", tmp_path / "wheels"
    files = tracked_package_files()
    for name in [*files, "pyproject.toml", "setup.py", "README.md"]:  # a clean tree: no earlier build/
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, source / name)
    env = {k: v for k, v in os.environ.items() if k != "FLEET_COMPILE"}  # the plain build
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "-w", wheels, source],
        check=True,
        capture_output=True,
        env=env,
    )
    (wheel,) = wheels.glob("fleet_telemetry-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = [name for name in files if name not in names]
    assert not missing, f"the wheel lacks {missing}: add them to [tool.setuptools.package-data]"
