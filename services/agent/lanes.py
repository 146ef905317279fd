"""What a run's sender has to send, by priority: a lane is a tail of the spooled run file (live data,
or a backfill up to where the gap ended) or a given list of messages (what the depot lacked after a
break, or what a pull asks for)."""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from services.agent.bandwidth import Priority
from services.hot.index import HotEntry
from services.hot.tail import HotIndexTail


@dataclass
class PullJob:
    """Chunks a pull (or a trigger's window) asks for: sent at its priority (a pull: behind live data
    and backfill), then asked about at the next check (a cut may have lost some: those are sent
    again), then done."""

    pull_id: str
    entries: list[HotEntry]
    priority: Priority = Priority.PULL
    chunks_sent: int = 0
    bytes_sent: int = 0
    written_at_check: int | None = None  # the check count when its last chunk was written
    done: asyncio.Event = field(default_factory=asyncio.Event)
    error: str | None = None

    def count(self, entry: HotEntry) -> None:
        self.chunks_sent += 1
        self.bytes_sent += entry.length


@dataclass
class Lane:
    """Messages waiting to be sent at one priority: a tail of the run file, or a given list."""

    priority: Priority
    tail: HotIndexTail | None = None
    end: int | None = None  # a tail's last offset (a backfill); None: follows the file (live)
    entries: deque[HotEntry] = field(default_factory=deque)
    on_sent: Callable[[HotEntry], None] | None = None
    job: PullJob | None = None

    def exhausted(self, size: int) -> bool:
        """Nothing left to send of a file of `size` bytes."""
        if self.entries:
            return False
        return self.tail is None or self.tail.position >= (size if self.end is None else min(self.end, size))
