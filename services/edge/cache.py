"""The chunk ids of sealed runs, as their committed `chunks.parquet` lists them, for the latest few
runs: a robot's agent asks about the same run again and again while it sends, and reading the
index from the warm store each time would cost a download per question."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from cachetools import TTLCache

MAX_RUNS = 32
MAX_IDS = 2_000_000  # about 150 MB of ids held at most, whatever the runs' sizes
TTL_S = 600.0  # an agent that stopped asking leaves nothing behind for long


@dataclass(frozen=True)
class _Entry:
    sha256: str
    ids: frozenset[bytes]


class SealedChunkIds:
    """An LRU of run id -> (the committed index's sha256, its chunk ids). Keyed by the digest the
    catalog committed, so a run sealed again (late data) is read afresh; thread-safe (the edge
    routes run on FastAPI's worker threads).

    Two bounds, runs and ids, and the newest run stays however many ids it has. cachetools'
    `TTLCache` bounds the ids (a run weighs its ids, at most the whole bound: one bigger than it
    pushes out all the others and is kept) and the time; the bound on runs is ours."""

    def __init__(
        self,
        max_runs: int = MAX_RUNS,
        max_ids: int = MAX_IDS,
        ttl_s: float = TTL_S,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.max_runs, self.max_ids, self.ttl_s, self.monotonic = max_runs, max_ids, ttl_s, monotonic
        self._entries: TTLCache[str, _Entry] = TTLCache(
            max_ids, ttl_s, timer=monotonic, getsizeof=lambda entry: min(len(entry.ids), max_ids)
        )
        self._lock = threading.Lock()
        self.loads = 0  # how many times an index was read (for tests and curiosity)

    def get(self, run_id: str, sha256: str, load: Callable[[], frozenset[bytes] | None]) -> frozenset[bytes]:
        """The chunk ids of `run_id`'s index with digest `sha256`: cached, else `load()`ed (outside
        the lock) and kept; a load that answers None (the store holds another index than the one
        committed) is answered as no ids and not kept."""
        with self._lock:
            entry = self._entries.get(run_id)
        if entry is not None and entry.sha256 == sha256:
            return entry.ids
        ids = load()
        with self._lock:
            self.loads += 1
            if ids is None:
                return frozenset()
            self._entries[run_id] = _Entry(sha256, ids)
            while len(self._entries) > max(self.max_runs, 1):
                self._entries.popitem()  # the least recently used
        return ids

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)
