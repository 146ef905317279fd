"""The modules every ingested chunk passes through, which an install made with ``FLEET_COMPILE=1``
compiles with mypyc (``setup.py``; deploy/Dockerfile does): the same mypy-strict Python, as C
extensions, about a third less CPU a one-row chunk (BENCHMARKS.md). Standard library only: the build
reads this file before anything is installed."""

from __future__ import annotations

import importlib.machinery
import importlib.util

MODULES = (
    "services/rrd/protowire.py",
    "services/rrd/frames.py",
    "services/rrd/messages.py",
    "services/rrd/decoder.py",
    "services/rrd/batch_plan.py",
    "services/rrd/layout.py",
    "services/rrd/chunk.py",
    "services/rrd/summary.py",
    "services/rrd/validate.py",
    "services/rrd/value_checks.py",
    "services/hot/index.py",
    "services/hot/store.py",
    "services/facts/run.py",
    "services/ingest/run.py",
    "services/ingest/replay.py",
    "services/ingest/source.py",
    "services/ingest/requests.py",
    "services/ingest/service.py",
    "services/api/h2_writes.py",
)


def module_names() -> list[str]:
    return [path.removesuffix(".py").replace("/", ".") for path in MODULES]


def compiled_modules() -> list[str]:
    """Those of `MODULES` that load as compiled extensions in this interpreter (imports none of
    them, only their packages)."""
    compiled = []
    for name in module_names():
        spec = importlib.util.find_spec(name)
        origin = spec.origin if spec is not None else None
        if origin is not None and origin.endswith(tuple(importlib.machinery.EXTENSION_SUFFIXES)):
            compiled.append(name)
    return compiled


def compiled_summary() -> str:
    """What `fleet serve` and the benchmarks say of this interpreter's ingest path."""
    done = len(compiled_modules())
    return f"{done} of {len(MODULES)} modules compiled" + (" (FLEET_COMPILE=1)" if done == len(MODULES) else "")
