"""Process-level tuning: start-up objects left out of later garbage collections; Arrow on the tuned
allocator."""

from __future__ import annotations

import gc
import subprocess
import sys
from collections.abc import Iterator

import pytest

from services.runtime import freeze_startup_objects


@pytest.fixture
def unfrozen() -> Iterator[None]:
    yield
    gc.unfreeze()  # the test process's objects go back to being collected


def test_start_up_objects_are_frozen_and_what_comes_after_is_still_collected(unfrozen: None):
    made_before = [[i] for i in range(1000)]
    frozen = freeze_startup_objects()
    assert frozen >= len(made_before)
    collected = {id(x) for generation in range(3) for x in gc.get_objects(generation=generation)}
    assert not any(id(x) in collected for x in made_before)  # none of them is walked by a collection

    class Cycle:
        pass

    cycle = Cycle()
    cycle.me = cycle  # type: ignore[attr-defined]
    del cycle
    assert gc.collect() >= 1  # garbage made after the freeze is collected as before


def test_arrow_allocates_from_the_tuned_allocator():
    """After `tune_allocator`, Arrow's buffers come from glibc's malloc as tuned (memory kept warm
    for reuse), not from Arrow's own mimalloc, whose first parses of a large index in the server ran
    several times slower. In a child process: the pool is the process's."""
    script = (
        "import pyarrow as pa\n"
        "from services.runtime import tune_allocator\n"
        "before = pa.default_memory_pool().backend_name\n"
        "tuned = tune_allocator()\n"
        "print(before, tuned, pa.default_memory_pool().backend_name)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True)
    _before, tuned, after = done.stdout.split()
    assert (tuned, after) == ("True", "system"), done.stdout
