"""A whole sealed run streamed from its store (`services.runs.sealed.stream_resumed`, and
`loop_resumed` for a store read on the event loop): a stream that breaks off is taken up again
where it stopped, and given up after a few breaks."""

from __future__ import annotations

import asyncio
import contextlib
import socket
import threading
from collections.abc import AsyncIterator, Iterator

import pytest

from services.runs.sealed import STREAM_ATTEMPTS, WholeOnLoop, loop_resumed, stream_resumed
from services.storage.objectstore import StorageError
from services.storage.splice import Source, splice_exactly

DATA = bytes(range(256)) * 40


class BreakingStore:
    """Streams DATA in pieces of 1000 bytes; the first `breaks` streams break off after 2500 bytes."""

    def __init__(self, breaks: int, short: bool = False) -> None:
        self.breaks, self.short = breaks, short
        self.opened: list[tuple[int, int | None]] = []

    def stream(self, key: str, start: int = 0, length: int | None = None) -> Iterator[bytes]:
        self.opened.append((start, length))
        end = len(DATA) if length is None else start + length
        for offset in range(start, end, 1000):
            if self.breaks and offset - start >= 2500:
                self.breaks -= 1
                if self.short:
                    return  # the store ended the body early without an error
                raise StorageError("connection reset")
            yield DATA[offset : min(offset + 1000, end)]

    async def loop_read(self, key: str, start: int, length: int) -> AsyncIterator[memoryview]:
        """As `stream`, on the event loop (a LoopReadingStore)."""
        for piece in self.stream(key, start, length):
            await asyncio.sleep(0)
            yield memoryview(piece)


async def _read_on_loop(store: BreakingStore) -> bytes:
    return b"".join([bytes(p) async for p in loop_resumed(store, "k", len(DATA))])  # type: ignore[arg-type]


@pytest.mark.parametrize("short", [False, True], ids=["reset", "ended-early"])
def test_a_stream_that_breaks_off_is_taken_up_where_it_stopped(short: bool):
    store = BreakingStore(breaks=2, short=short)
    assert b"".join(stream_resumed(store, "k", len(DATA))) == DATA  # type: ignore[arg-type]
    assert [start for start, _ in store.opened] == [0, 3000, 6000]
    assert all(start + (length or 0) == len(DATA) for start, length in store.opened)


def test_a_stream_that_keeps_breaking_fails_the_download():
    store = BreakingStore(breaks=STREAM_ATTEMPTS)
    with pytest.raises(StorageError, match="connection reset"):
        b"".join(stream_resumed(store, "k", len(DATA)))  # type: ignore[arg-type]
    assert len(store.opened) == STREAM_ATTEMPTS


@pytest.mark.parametrize("short", [False, True], ids=["reset", "ended-early"])
def test_a_read_on_the_loop_that_breaks_off_is_taken_up_where_it_stopped(short: bool):
    store = BreakingStore(breaks=2, short=short)
    assert asyncio.run(_read_on_loop(store)) == DATA
    assert store.opened == [(0, len(DATA)), (3000, len(DATA) - 3000), (6000, len(DATA) - 6000)]


def test_a_read_on_the_loop_that_keeps_breaking_fails_the_download():
    store = BreakingStore(breaks=STREAM_ATTEMPTS)
    with pytest.raises(StorageError, match="connection reset"):
        asyncio.run(_read_on_loop(store))
    assert len(store.opened) == STREAM_ATTEMPTS


LEADING = 100  # bytes of each GET's body that come with its head


class SplicingStore(BreakingStore):
    """As BreakingStore, its GETs handed over (`loop_open`): LEADING bytes with the head, the rest on
    a socket a thread fills, the first `breaks` of them closed after 2500 bytes."""

    def loop_splices(self) -> bool:
        return True

    @contextlib.asynccontextmanager
    async def loop_open(self, key: str, start: int, length: int) -> AsyncIterator[Source]:
        self.opened.append((start, length))
        body = DATA[start : start + length]
        if self.breaks:
            self.breaks -= 1
            body = body[:2500]
        feeder, sock = socket.socketpair()
        sock.setblocking(False)
        thread = threading.Thread(target=_feed, args=(feeder, body[LEADING:]))
        thread.start()
        try:
            yield Source(body[:LEADING], sock.fileno(), length - LEADING, stall_s=10)
        finally:
            sock.close()
            await asyncio.to_thread(thread.join)


def _feed(sock: socket.socket, data: bytes) -> None:
    with sock:
        sock.sendall(data)


async def _spliced(store: SplicingStore) -> bytes:
    """The object as `send_by_splice` sends it: written bytes, and spliced ones read off a socket."""
    out, client = socket.socketpair()
    out.setblocking(False)
    client.setblocking(False)
    received = bytearray()
    loop = asyncio.get_running_loop()

    async def write(data: bytes) -> None:
        await loop.sock_sendall(out, data)

    async def splice(source: Source) -> None:
        await splice_exactly(source.fd, out.fileno(), source.left, source.stall_s)

    async def read() -> None:
        while more := await loop.sock_recv(client, 65536):
            received.extend(more)

    reading = asyncio.create_task(read())
    try:
        await WholeOnLoop(store, "k", len(DATA)).send_by_splice(write, splice)  # type: ignore[arg-type]
    finally:
        out.close()
        await reading
        client.close()
    return bytes(received)


def test_a_spliced_read_that_breaks_off_is_taken_up_where_it_stopped():
    store = SplicingStore(breaks=2)
    assert asyncio.run(_spliced(store)) == DATA
    assert store.opened == [(0, len(DATA)), (2500, len(DATA) - 2500), (5000, len(DATA) - 5000)]


def test_a_spliced_read_that_keeps_breaking_fails_the_download():
    store = SplicingStore(breaks=STREAM_ATTEMPTS)
    with pytest.raises(StorageError, match="broke off after 7500 of 10240 bytes: the source ended early"):
        asyncio.run(_spliced(store))
    assert len(store.opened) == STREAM_ATTEMPTS
