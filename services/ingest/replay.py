"""What `ReadMessages` readers get: a bounded replay of the live streams' recent history, then new
messages as they are filed.

History is kept for live runs only, by bytes (`FLEET_REPLAY_BYTES`): a run's store infos and
blueprint messages stay while it is live; past the budget the oldest temporal chunks go first,
then the oldest static ones (the same rule as Rerun's own proxy); when a run closes, all of its
history goes. Readers that fall too far behind are disconnected rather than
allowed to slow ingest down; they can connect again.
"""

from __future__ import annotations

import asyncio
import collections
import logging

from services.rrd.protowire import log_msg_envelope

log = logging.getLogger(__name__)

READER_QUEUE = 4096
# Messages up to this size are kept as a copy of their own bytes rather than a view of the request.
# A view is two objects the garbage collector tracks for as long as the history holds it, and a
# full collection walks them all: with 64 MiB of one-row chunks, some 200,000 objects and 20-40 ms
# a collection. A copy is one untracked object, and its tuples (the kind made a plain int: an enum
# member is tracked) are untracked by the first collections that see them. Large messages are few,
# and stay views: copying them would cost more than walking them.
COPY_BELOW = 64 * 1024
Message = tuple[int, bytes | bytearray | memoryview]  # (kind, the message's protobuf bytes)


def read_response(kind: int, raw: bytes | bytearray | memoryview) -> bytes:
    """A serialized `ReadMessagesResponse` around a message's own bytes (see `log_msg_envelope`)."""
    return log_msg_envelope(kind, raw)


_Entry = tuple[str, Message]  # (run id, message): a plain tuple, the cheapest thing to make per chunk


class ReplayHub:
    """History per live run: when a run closes its messages leave the history (and its bytes the
    budget), so a reader that connects later gets what is live now, not what was."""

    def __init__(self, budget_bytes: int) -> None:
        self.budget = budget_bytes
        self._persistent: dict[str, list[Message]] = {}  # per live run, in order
        self._static: collections.deque[_Entry] = collections.deque()
        self._temporal: collections.deque[_Entry] = collections.deque()
        self._run_bytes: dict[str, int] = {}  # bytes held per live run
        self._size = 0
        self._stale = 0  # entries in the deques whose run has ended (dropped lazily)
        self._readers: set[asyncio.Queue[Message | None]] = set()

    @property
    def held_bytes(self) -> int:
        return self._size

    @property
    def live_runs(self) -> int:
        return len(self._run_bytes)

    def publish(
        self, run_id: str, kind: int, raw: bytes | bytearray | memoryview, *, persistent: bool, static: bool
    ) -> None:
        # Kept as the message's own bytes; wrapped when sent.
        response: Message = (int(kind), bytes(raw) if len(raw) < COPY_BELOW else raw)
        if persistent:
            self._persistent.setdefault(run_id, []).append(response)
        elif static:
            self._static.append((run_id, response))
        else:
            self._temporal.append((run_id, response))
        self._run_bytes[run_id] = self._run_bytes.get(run_id, 0) + len(raw)
        self._size += len(raw)
        if self._size > self.budget:
            self._shrink()
        if not self._readers:
            return
        for queue in list(self._readers):
            try:
                queue.put_nowait(response)
            except asyncio.QueueFull:  # too far behind: let it go rather than slow ingest down
                self._readers.discard(queue)
                queue.get_nowait()
                queue.put_nowait(None)

    def end_run(self, run_id: str) -> None:
        """The run closed: its history goes (readers already connected keep what they were sent)."""
        held = self._run_bytes.pop(run_id, None)
        if held is None:
            return
        self._size -= held
        self._persistent.pop(run_id, None)
        self._stale += sum(1 for entry in self._static if entry[0] == run_id)
        self._stale += sum(1 for entry in self._temporal if entry[0] == run_id)
        if self._stale > len(self._static) + len(self._temporal) - self._stale:
            self._compact()

    def _shrink(self) -> None:
        """Past the budget the oldest temporal chunks go first, then the oldest static ones."""
        while self._size > self.budget and (self._temporal or self._static):
            run_id, (_, raw) = self._temporal.popleft() if self._temporal else self._static.popleft()
            if run_id not in self._run_bytes:
                self._stale -= 1
                continue
            self._size -= len(raw)
            self._run_bytes[run_id] -= len(raw)

    def _compact(self) -> None:
        self._static = collections.deque(e for e in self._static if e[0] in self._run_bytes)
        self._temporal = collections.deque(e for e in self._temporal if e[0] in self._run_bytes)
        self._stale = 0

    def subscribe(self) -> tuple[list[Message], asyncio.Queue[Message | None]]:
        """The history to send first (persistent, static, temporal), and a queue of what follows;
        wrap each with `read_response` to send it."""
        queue: asyncio.Queue[Message | None] = asyncio.Queue(READER_QUEUE)
        self._readers.add(queue)
        live = self._run_bytes
        history = [m for messages in self._persistent.values() for m in messages]
        history += [message for run_id, message in self._static if run_id in live]
        history += [message for run_id, message in self._temporal if run_id in live]
        return history, queue

    def unsubscribe(self, queue: asyncio.Queue[Message | None]) -> None:
        self._readers.discard(queue)
