"""The bounded cache of what the catalog server keeps of runs between queries."""

from __future__ import annotations

from services.redap.cache import WeightedLru


def test_the_least_recently_used_entries_go_once_the_weight_is_over():
    cache: WeightedLru[list[int]] = WeightedLru(10, len)
    cache.put("a", [1] * 4)
    cache.put("b", [2] * 4)
    assert cache.get("a") == [1] * 4  # `a` is now the most recently used
    cache.put("c", [3] * 4)
    assert cache.get("b") is None and cache.get("a") is not None and cache.get("c") is not None
    cache.put("huge", [0] * 11)  # alone over the bound: answered, not kept
    assert cache.get("huge") is None and len(cache) == 2


def test_get_or_load_loads_once_while_kept():
    cache: WeightedLru[str] = WeightedLru(2)
    loads: list[str] = []

    def load() -> str:
        loads.append("x")
        return "value"

    assert cache.get_or_load("k", load) == cache.get_or_load("k", load) == "value"
    assert loads == ["x"]
    cache.put("k", "replaced")
    assert cache.get("k") == "replaced" and len(cache) == 1
    cache.clear()
    assert cache.get("k") is None
