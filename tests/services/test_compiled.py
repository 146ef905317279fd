"""The compiled build (``FLEET_COMPILE=1``): the modules it compiles are named once
(`services/compiled.py`), setup.py compiles exactly those and only when asked, and a build made to
be compiled loads every one of them compiled (the CI's compiled stage sets FLEET_EXPECT_COMPILED)."""

from __future__ import annotations

import importlib
import os
import runpy
import subprocess
import sys
import types
from pathlib import Path
from typing import Any

import pytest

from services.compiled import MODULES, compiled_modules, module_names

ROOT = Path(__file__).resolve().parents[2]


def test_every_listed_module_is_a_module_of_the_package():
    assert len(set(MODULES)) == len(MODULES)
    for path, name in zip(MODULES, module_names(), strict=True):
        assert (ROOT / path).is_file(), path
        assert importlib.import_module(name).__name__ == name


def _ext_modules(
    monkeypatch: pytest.MonkeyPatch, compile_flag: str | None, argv: tuple[str, ...] = ("setup.py", "bdist_wheel")
) -> tuple[Any, list[list[str]]]:
    calls: list[list[str]] = []

    def mypycify(paths: list[str], **_: Any) -> list[str]:
        calls.append(list(paths))
        return ["extension"]

    fake = types.ModuleType("mypyc.build")
    fake.mypycify = mypycify  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "mypyc.build", fake)
    if compile_flag is None:
        monkeypatch.delenv("FLEET_COMPILE", raising=False)
    else:
        monkeypatch.setenv("FLEET_COMPILE", compile_flag)
    monkeypatch.chdir(ROOT)
    monkeypatch.setattr(sys, "argv", list(argv))
    setup = runpy.run_path(str(ROOT / "setup.py"), run_name="setup_under_test")
    return setup["ext_modules"](), calls


def test_setup_compiles_nothing_unless_asked(monkeypatch: pytest.MonkeyPatch):
    for flag in (None, "", "0", "yes"):
        extensions, calls = _ext_modules(monkeypatch, flag)
        assert extensions == [] and calls == []


def test_setup_compiles_the_listed_modules(monkeypatch: pytest.MonkeyPatch):
    extensions, calls = _ext_modules(monkeypatch, "1")
    assert extensions == ["extension"]
    (paths,) = calls
    assert [p for p in paths if not p.startswith("--")] == list(MODULES)
    assert "--no-site-packages" in paths  # the same code compiled wherever the build runs


def test_setup_refuses_to_compile_an_editable_install(monkeypatch: pytest.MonkeyPatch):
    with pytest.raises(SystemExit, match="editable install"):
        _ext_modules(monkeypatch, "1", ("setup.py", "editable_wheel", "--dist-dir", "x"))
    extensions, _ = _ext_modules(monkeypatch, None, ("setup.py", "editable_wheel"))
    assert extensions == []  # the plain editable install of the quick start


@pytest.mark.skipif(os.environ.get("FLEET_EXPECT_COMPILED") != "1", reason="not a build made to be compiled")
def test_a_compiled_build_loads_every_module_compiled():
    assert compiled_modules() == module_names()


@pytest.mark.skipif(os.environ.get("FLEET_EXPECT_COMPILED") != "1", reason="not a build made to be compiled")
def test_servers_started_by_the_tests_run_it_compiled(tmp_path: Path):
    """`fleet serve` started by a test (another process, its own working directory) loads the
    compiled modules too, so the end-to-end suites exercise them."""
    code = "from services.compiled import compiled_modules; print(','.join(compiled_modules()))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, check=True)
    assert out.stdout.strip().split(",") == module_names()
