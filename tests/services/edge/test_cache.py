"""The sealed chunk ids cache: one read per run and committed digest, bounded by runs, ids and time."""

from __future__ import annotations

from collections.abc import Callable

from services.edge.cache import SealedChunkIds


class Loads:
    """A loader that counts its calls and answers `ids` (None: an index the catalog did not commit)."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def __call__(self, name: str, ids: frozenset[bytes] | None) -> Callable[[], frozenset[bytes] | None]:
        def load() -> frozenset[bytes] | None:
            self.calls.append(name)
            return ids

        return load


def ids(*numbers: int) -> frozenset[bytes]:
    return frozenset(n.to_bytes(16, "big") for n in numbers)


def test_one_read_per_run_and_digest():
    cache, loads = SealedChunkIds(), Loads()
    assert cache.get("run", "sha-1", loads("a", ids(1, 2))) == ids(1, 2)
    assert cache.get("run", "sha-1", loads("b", ids(9))) == ids(1, 2)  # cached
    assert cache.get("run", "sha-2", loads("c", ids(3))) == ids(3)  # sealed again: read afresh
    assert loads.calls == ["a", "c"] and len(cache) == 1


def test_an_uncommitted_index_is_no_ids_and_not_kept():
    cache, loads = SealedChunkIds(), Loads()
    assert cache.get("run", "sha-1", loads("a", None)) == frozenset()
    assert cache.get("run", "sha-1", loads("b", ids(1))) == ids(1)
    assert loads.calls == ["a", "b"]


def test_the_least_recently_used_runs_go_first():
    cache, loads = SealedChunkIds(max_runs=2), Loads()
    cache.get("r1", "s", loads("r1", ids(1)))
    cache.get("r2", "s", loads("r2", ids(2)))
    cache.get("r1", "s", loads("r1 again", ids(1)))  # r1 used last: r2 goes
    cache.get("r3", "s", loads("r3", ids(3)))
    cache.get("r1", "s", loads("r1 third", ids(1)))
    cache.get("r2", "s", loads("r2 again", ids(2)))
    assert loads.calls == ["r1", "r2", "r3", "r2 again"]


def test_ids_held_are_bounded_but_the_newest_run_stays():
    cache, loads = SealedChunkIds(max_ids=3), Loads()
    cache.get("small", "s", loads("small", ids(1, 2)))
    cache.get("big", "s", loads("big", ids(3, 4, 5, 6)))  # over the bound alone: kept, the older one goes
    assert len(cache) == 1
    cache.get("big", "s", loads("big again", ids()))
    assert loads.calls == ["small", "big"]


def test_entries_expire():
    now = [100.0]
    cache, loads = SealedChunkIds(ttl_s=60, monotonic=lambda: now[0]), Loads()
    cache.get("run", "s", loads("a", ids(1)))
    now[0] += 59
    cache.get("run", "s", loads("b", ids(1)))
    now[0] += 2
    cache.get("run", "s", loads("c", ids(1)))
    assert loads.calls == ["a", "c"]
