"""The wheel pip builds from the repository (what the image installs, deploy/Dockerfile) holds every
file of the packages: a template or an asset left out of it fails only once deployed."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.deploy.deploy_files import ROOT, build_sources


def tracked_package_files(packages: list[str]) -> list[str]:
    listed = subprocess.run(["git", "ls-files", *packages], cwd=ROOT, capture_output=True, text=True, check=True)
    return [name for name in listed.stdout.splitlines() if not name.endswith("/.gitignore")]


@pytest.mark.slow
def test_the_wheel_holds_every_file_of_the_packages(tmp_path: Path):
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout: the package's files are what git tracks")
    source, wheels = tmp_path / "src", tmp_path / "wheels"
    packages, beside = build_sources()
    files = tracked_package_files(packages)
    for name in [*files, *beside]:  # a clean tree: no earlier build/
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
