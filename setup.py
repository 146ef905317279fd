"""Build hook of the package (the metadata is pyproject.toml's). With ``FLEET_COMPILE=1`` the ingest
hot path (`services/compiled.py`) is compiled with mypyc into C extensions beside the modules; without
it, the package is plain Python. Compile only installs that are not editable (``pip install .``,
deploy/Dockerfile): an extension shadows its .py, so edits to a compiled module would not be seen."""

from __future__ import annotations

import os
import runpy
import sys
from typing import Any

from setuptools import setup


def ext_modules() -> list[Any]:
    if os.environ.get("FLEET_COMPILE", "") != "1":
        return []
    if "editable_wheel" in sys.argv:  # how setuptools builds `pip install -e`
        raise SystemExit(
            "FLEET_COMPILE=1 with an editable install would put compiled modules beside their sources, "
            "and they would shadow every later edit: install with `pip install .`, or leave FLEET_COMPILE unset"
        )
    from mypyc.build import mypycify

    modules = runpy.run_path(os.path.join("services", "compiled.py"))["MODULES"]
    # pip builds in an environment of its own, without the dependencies: what they export is typed
    # Any here, wherever the build runs, so every build compiles the same code (CI's mypy --strict
    # checks the real types; compiled code checks ours as it runs).
    lenient = [
        "--no-site-packages",
        "--ignore-missing-imports",
        "--allow-subclassing-any",
        "--allow-untyped-decorators",
        "--no-warn-return-any",
        "--allow-any-generics",
    ]
    return list(mypycify([*lenient, *modules], opt_level="3"))


if __name__ == "__main__":  # as setuptools runs it (tests load the module to check ext_modules)
    setup(ext_modules=ext_modules())
