"""Process-level tuning: start-up objects left out of later garbage collections."""

from __future__ import annotations

import gc
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
