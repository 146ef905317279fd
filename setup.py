"""Build hook of the package (the metadata is pyproject.toml's). With ``FLEET_COMPILE=1`` the ingest
hot path (`services/compiled.py`) is compiled with mypyc into C extensions beside the modules; without
it, the package is plain Python. Compile only installs that are not editable (``pip install .``,
deploy/Dockerfile): an extension shadows its .py, so edits to a compiled module would not be seen."""

from __future__ import annotations

import os
import runpy
from typing import Any

from setuptools import setup


def ext_modules() -> list[Any]:
    if os.environ.get("FLEET_COMPILE", "") != "1":
        return []
    from mypyc.build import mypycify

    modules = runpy.run_path(os.path.join("services", "compiled.py"))["MODULES"]
    # pip builds in an environment of its own, without the dependencies: what they export is typed
    # Any here (CI's mypy --strict checks the real types; compiled code checks them as it runs).
    lenient = [
        "--ignore-missing-imports",
        "--allow-subclassing-any",
        "--allow-untyped-decorators",
        "--no-warn-return-any",
        "--allow-any-generics",
    ]
    return list(mypycify([*lenient, *modules], opt_level="3"))


if __name__ == "__main__":  # as setuptools runs it (tests load the module to check ext_modules)
    setup(ext_modules=ext_modules())
