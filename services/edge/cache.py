"""The chunk ids of sealed runs, as their committed `chunks.parquet` lists them, for the latest few
runs: a robot's agent asks about the same run again and again while it sends, and reading the
index from the warm store each time would cost a download per question."""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

MAX_RUNS = 32
MAX_IDS = 2_000_000  # about 150 MB of ids held at most, whatever the runs' sizes
TTL_S = 600.0  # an agent that stopped asking leaves nothing behind for long


@dataclass(frozen=True)
class _Entry:
    sha256: str
    ids: frozenset[bytes]
    expires_at: float


class SealedChunkIds:
    """An LRU of run id -> (the committed index's sha256, its chunk ids). Keyed by the digest the
    catalog committed, so a run sealed again (late data) is read afresh; thread-safe (the edge
    routes run on FastAPI's worker threads)."""

    def __init__(
        self,
        max_runs: int = MAX_RUNS,
        max_ids: int = MAX_IDS,
        ttl_s: float = TTL_S,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.max_runs, self.max_ids, self.ttl_s, self.monotonic = max_runs, max_ids, ttl_s, monotonic
        self._entries: OrderedDict[str, _Entry] = OrderedDict()
        self._lock = threading.Lock()
        self.loads = 0  # how many times an index was read (for tests and curiosity)

    def get(self, run_id: str, sha256: str, load: Callable[[], frozenset[bytes] | None]) -> frozenset[bytes]:
        """The chunk ids of `run_id`'s index with digest `sha256`: cached, else `load()`ed (outside
        the lock) and kept; a load that answers None (the store holds another index than the one
        committed) is answered as no ids and not kept."""
        now = self.monotonic()
        with self._lock:
            entry = self._entries.get(run_id)
            if entry is not None and entry.sha256 == sha256 and entry.expires_at > now:
                self._entries.move_to_end(run_id)
                return entry.ids
        ids = load()
        with self._lock:
            self.loads += 1
            if ids is None:
                return frozenset()
            self._entries[run_id] = _Entry(sha256, ids, now + self.ttl_s)
            self._entries.move_to_end(run_id)
            self._evict()
        return ids

    def _evict(self) -> None:
        """Drop the least recently used runs past the limits (the newest one stays, however big)."""
        held = sum(len(e.ids) for e in self._entries.values())
        while len(self._entries) > 1 and (len(self._entries) > self.max_runs or held > self.max_ids):
            _, dropped = self._entries.popitem(last=False)
            held -= len(dropped.ids)

    def __len__(self) -> int:
        return len(self._entries)
