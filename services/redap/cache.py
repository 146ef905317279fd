"""A small thread-safe LRU cache bounded by a weight (entries, rows): what the catalog server keeps
of runs between queries, so memory stays bounded whatever the number of runs held. cachetools'
`LRUCache` does the bookkeeping; what is ours is the lock (it is shared by the gRPC worker threads,
and an LRU reorders on every read) and that a value too heavy to keep is still answered."""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

from cachetools import LRUCache

V = TypeVar("V")


class WeightedLru(Generic[V]):
    def __init__(self, max_weight: int, weigh: Callable[[V], int] = lambda _: 1) -> None:
        self.max_weight = max_weight
        self._items: LRUCache[Hashable, V] = LRUCache(max_weight, getsizeof=weigh)
        self._lock = threading.Lock()

    def get(self, key: Hashable) -> V | None:
        with self._lock:
            return self._items.get(key)

    def put(self, key: Hashable, value: V) -> V:
        """Keep `value` (unless it alone outweighs the cache), evicting the least recently used."""
        with self._lock:
            try:
                self._items[key] = value
            except ValueError:  # too heavy to keep: answered, and what the key held before is stale
                self._items.pop(key, None)
        return value

    def get_or_load(self, key: Hashable, load: Callable[[], V]) -> V:
        """The cached value, or `load()` kept. Two threads missing at once both load (the loads are
        reads of immutable objects: the same answer, at worst twice the work)."""
        found = self.get(key)
        return found if found is not None else self.put(key, load())

    def clear(self) -> None:
        with self._lock:
            self._items.clear()

    def __len__(self) -> int:
        with self._lock:
            return len(self._items)
