"""Bytes moved from one socket to another inside the kernel: splice(2) through a pipe.

Nothing is copied into Python, and the event loop runs one callback per read however much it moved.
Relaying the store's GET of a whole warm download this way took half the CPU of a relay that reads
into a buffer and writes it out (0.17 against 0.37 s per GiB, BENCHMARKS.md), and on a machine whose
cores the store, the depot and the client share, the CPU is the speed. Linux only, plain TCP or Unix
sockets only (TLS bytes must pass through Python to be decrypted).

Two users: the gRPC front passes a connection on (`Splice`, until either side ends), and a whole
warm download hands the rest of the store's answer to the client's connection (`splice_exactly`, a
count of bytes, awaited).
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import fcntl
import os
from collections.abc import Callable
from dataclasses import dataclass

# How an ASGI app asks the server to splice into the client's connection: the server lists the
# extension in a request's scope where it can (services/api/http_protocol.py), and the app, its
# response started with a Content-Length, sends {"type": SPLICE_MESSAGE, "fd": socket, "count": n,
# "stall_s": t} in place of n bytes of body. The server raises SourceEnded if the socket ends first
# or sends nothing for t seconds while the client waits on it.
SPLICE_EXTENSION = "fleet.splice"
SPLICE_MESSAGE = "fleet.splice.body"
PIPE_BYTES = 1 << 20  # asked for each splice's pipe (Linux grants up to fs/pipe-max-size, 1 MiB by default)
_FLAGS = os.SPLICE_F_MOVE | os.SPLICE_F_NONBLOCK


class Ending(enum.Enum):
    """Why a splice stopped."""

    LIMIT = "limit"  # the bytes it was asked to move have reached the destination
    SOURCE_ENDED = "source ended"  # the source closed or was reset; all it sent has been moved on
    DESTINATION_FAILED = "destination failed"  # the destination closed or was reset
    CLOSED = "closed"  # stopped by its owner


class Splice:
    """Moves the bytes of `src` to `dst` (file descriptors of sockets registered with `loop`) until
    the source ends, `limit` bytes have moved (if given), or the destination fails; then closes its
    pipe and calls `done` once with the ending. Reads nothing while the destination cannot take more
    (back-pressure). It closes neither socket."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        src: int,
        dst: int,
        done: Callable[[Ending], None],
        limit: int | None = None,
    ) -> None:
        self._loop, self._src, self._dst, self._done, self._limit = loop, src, dst, done, limit
        self._read_end, self._write_end = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        with contextlib.suppress(OSError):  # a larger pipe moves more per call
            fcntl.fcntl(self._write_end, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
        self._room = fcntl.fcntl(self._write_end, fcntl.F_GETPIPE_SZ)
        self._held = 0  # bytes in the pipe
        self._source_done = False  # ended, or `limit` bytes taken from it
        self.taken = 0  # bytes read from the source
        self.moved = 0  # bytes written to the destination
        self.closed = False
        self.reading = True  # waiting on the source (not held back by the destination)
        if limit == 0:
            self._finish(Ending.LIMIT)
            return
        loop.add_reader(self._src, self._readable)

    def _readable(self) -> None:
        want = self._room - self._held
        if self._limit is not None:
            want = min(want, self._limit - self.taken)
        try:
            got = os.splice(self._src, self._write_end, want, flags=_FLAGS)
        except BlockingIOError:
            return
        except OSError:
            got = 0  # reset by the peer: the same as its end
        self.taken += got
        self._held += got
        if got == 0 or self.taken == self._limit:
            self._source_done = True
            self._loop.remove_reader(self._src)
        self._flush()

    def _flush(self) -> None:
        try:
            while self._held:
                sent = os.splice(self._read_end, self._dst, self._held, flags=_FLAGS)
                self._held -= sent
                self.moved += sent
        except BlockingIOError:  # the destination is full: wait until it drains, reading nothing
            if not self._source_done:
                self._loop.remove_reader(self._src)
            self.reading = False
            self._loop.add_writer(self._dst, self._writable)
            return
        except OSError:
            self._finish(Ending.DESTINATION_FAILED)
            return
        if self._source_done:
            self._finish(Ending.LIMIT if self.moved == self._limit else Ending.SOURCE_ENDED)

    def _writable(self) -> None:
        self._loop.remove_writer(self._dst)
        self._flush()
        if not self.closed and not self._held and not self._source_done:
            self.reading = True
            self._loop.add_reader(self._src, self._readable)

    def close(self) -> None:
        """Stop moving bytes (`done` is told CLOSED if it had not ended)."""
        self._finish(Ending.CLOSED)

    def _finish(self, ending: Ending) -> None:
        if self.closed:
            return
        self.closed = True
        self._loop.remove_reader(self._src)
        self._loop.remove_writer(self._dst)
        os.close(self._read_end)
        os.close(self._write_end)
        self._done(ending)


@dataclass(frozen=True)
class Source:
    """An answer whose body is taken from its socket by splice (a store's GET, its head read)."""

    leading: bytes  # the body's first bytes, which came with the head: sent before the splice
    fd: int  # the socket (non-blocking), its next byte the one after `leading`; its owner closes it
    left: int  # bytes of the body still to come on it
    stall_s: float  # how long it may send nothing before it is given up (its store's read timeout)


class SpliceBroke(Exception):
    """A counted splice stopped short: `moved` bytes reached the destination."""

    def __init__(self, moved: int, why: str) -> None:
        super().__init__(why)
        self.moved = moved


class SourceEnded(SpliceBroke):
    """The source closed, was reset, or sent nothing for the stall timeout."""


class DestinationFailed(SpliceBroke):
    """The destination closed or was reset."""


async def splice_exactly(src: int, dst: int, count: int, stall_s: float) -> None:
    """Move `count` bytes from socket `src` to socket `dst` (non-blocking sockets, which may belong
    to transports: the loop watches duplicates of them, so the transports' own registrations are
    untouched; a transport must neither read `src` nor write `dst` meanwhile). Raises SourceEnded
    if the source ends first or sends nothing for `stall_s` seconds while the destination waits on
    it, DestinationFailed if the destination fails; both carry the bytes moved."""
    loop = asyncio.get_running_loop()
    ended: asyncio.Future[Ending] = loop.create_future()

    def done(ending: Ending) -> None:
        if not ended.done():
            ended.set_result(ending)

    src_dup, dst_dup = os.dup(src), os.dup(dst)
    try:
        splice = Splice(loop, src_dup, dst_dup, done, limit=count)
        try:
            while not ended.done():
                taken = splice.taken
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(asyncio.shield(ended), stall_s)
                if not ended.done() and splice.taken == taken and splice.reading:
                    raise SourceEnded(splice.moved, f"the source sent nothing for {stall_s:g} s")
        finally:
            splice.close()
    finally:
        os.close(src_dup)
        os.close(dst_dup)
    ending = ended.result()
    if ending is Ending.DESTINATION_FAILED:
        raise DestinationFailed(splice.moved, "the destination closed")
    if ending is not Ending.LIMIT:
        raise SourceEnded(splice.moved, "the source ended early")
