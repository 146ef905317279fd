"""What `ReadMessages` readers get: a bounded replay of the live streams' recent history, then new
messages as they are filed.

History is kept by bytes (`FLEET_REPLAY_BYTES`): store infos and blueprint messages are never
dropped; past the budget the oldest temporal chunks go first, then the oldest static ones (the
same rule as Rerun's own proxy). Readers that fall too far behind are disconnected rather than
allowed to slow ingest down; they can connect again.
"""

from __future__ import annotations

import asyncio
import collections
import logging

log = logging.getLogger(__name__)

READER_QUEUE = 4096
Message = tuple[int, bytes | bytearray | memoryview]  # (kind, the message's protobuf bytes)


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def read_response(kind: int, raw: bytes | bytearray | memoryview) -> bytes:
    """A serialized `ReadMessagesResponse { LogMsg log_msg = 1 }` around a message's own bytes
    (LogMsg's oneof field numbers are the message kinds 1-3): nothing is re-encoded."""
    inner = bytes([(kind << 3) | 2]) + _varint(len(raw)) + bytes(raw)
    return bytes([(1 << 3) | 2]) + _varint(len(inner)) + inner


class ReplayHub:
    def __init__(self, budget_bytes: int) -> None:
        self.budget = budget_bytes
        self._persistent: list[Message] = []
        self._static: collections.deque[Message] = collections.deque()
        self._temporal: collections.deque[Message] = collections.deque()
        self._size = 0
        self._readers: set[asyncio.Queue[Message | None]] = set()

    @property
    def held_bytes(self) -> int:
        return self._size

    def publish(self, kind: int, raw: bytes | bytearray | memoryview, *, persistent: bool, static: bool) -> None:
        # Kept as the message's own bytes (a view of the request, no copy); wrapped when sent.
        response: Message = (kind, raw)
        if persistent:
            self._persistent.append(response)
        elif static:
            self._static.append(response)
        else:
            self._temporal.append(response)
        self._size += len(raw)
        while self._size > self.budget and (self._temporal or self._static):
            dropped = self._temporal.popleft() if self._temporal else self._static.popleft()
            self._size -= len(dropped[1])
        for queue in list(self._readers):
            try:
                queue.put_nowait(response)
            except asyncio.QueueFull:  # too far behind: let it go rather than slow ingest down
                self._readers.discard(queue)
                queue.get_nowait()
                queue.put_nowait(None)

    def subscribe(self) -> tuple[list[Message], asyncio.Queue[Message | None]]:
        """The history to send first (persistent, static, temporal), and a queue of what follows;
        wrap each with `read_response` to send it."""
        queue: asyncio.Queue[Message | None] = asyncio.Queue(READER_QUEUE)
        self._readers.add(queue)
        return [*self._persistent, *self._static, *self._temporal], queue

    def unsubscribe(self, queue: asyncio.Queue[Message | None]) -> None:
        self._readers.discard(queue)
