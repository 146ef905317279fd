"""`services.storage.splice`: bytes moved between sockets inside the kernel. A counted splice moves
exactly its count and leaves what follows in the source, waits while the destination is full,
names what it moved when the source ends, stalls or the destination goes away, and closes every
file descriptor it opened; the open-ended one (the gRPC front's) runs to the source's end."""

from __future__ import annotations

import asyncio
import os
import socket

import pytest

from services.storage.splice import DestinationFailed, Ending, SourceEnded, Splice, splice_exactly


def pair() -> tuple[socket.socket, socket.socket]:
    """A connected loopback TCP pair, both non-blocking (as the event loop's sockets are)."""
    listener = socket.create_server(("127.0.0.1", 0))
    a = socket.create_connection(listener.getsockname())
    b, _ = listener.accept()
    listener.close()
    for sock in (a, b):
        sock.setblocking(False)
    return a, b


async def read_exactly(sock: socket.socket, count: int) -> bytes:
    loop = asyncio.get_running_loop()
    data = bytearray()
    while len(data) < count:
        more = await loop.sock_recv(sock, count - len(data))
        if not more:
            break
        data += more
    return bytes(data)


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_a_counted_splice_moves_its_count_and_leaves_the_rest_in_the_source():
    async def main() -> None:
        store_side, source = pair()
        destination, client_side = pair()
        payload = os.urandom(5_000_000)
        fds = open_fds()
        loop = asyncio.get_running_loop()
        sending = asyncio.create_task(loop.sock_sendall(store_side, payload + b"NEXT"))
        receiving = asyncio.create_task(read_exactly(client_side, len(payload)))
        await splice_exactly(source.fileno(), destination.fileno(), len(payload), stall_s=5)
        assert await receiving == payload
        await sending
        assert await read_exactly(source, 4) == b"NEXT"  # not taken: it was past the count
        assert open_fds() == fds  # its pipe and the sockets' duplicates are closed
        for sock in (store_side, source, destination, client_side):
            sock.close()

    asyncio.run(main())


def test_a_full_destination_holds_the_splice_back_until_it_reads():
    async def main() -> None:
        store_side, source = pair()
        destination, client_side = pair()
        payload = os.urandom(20_000_000)  # far more than two sockets' buffers and the pipe hold
        loop = asyncio.get_running_loop()
        sending = asyncio.create_task(loop.sock_sendall(store_side, payload))
        # (a stall timeout long enough that a busy machine's scheduling does not pass for one: the
        # source is fed from this same loop, so a process held off the CPU resumes with the timer due)
        splicing = asyncio.create_task(splice_exactly(source.fileno(), destination.fileno(), len(payload), stall_s=0.5))
        await asyncio.sleep(1.5)  # the client reads nothing for three stall timeouts: not a stall
        assert not splicing.done()
        assert await read_exactly(client_side, len(payload)) == payload
        await splicing
        await sending
        for sock in (store_side, source, destination, client_side):
            sock.close()

    asyncio.run(main())


@pytest.mark.parametrize("how", ["closed", "reset"])
def test_a_source_that_ends_early_names_what_was_moved(how: str):
    async def main() -> None:
        store_side, source = pair()
        destination, client_side = pair()
        sent = os.urandom(100_000)  # less than loopback sockets buffer: no reader needed meanwhile
        store_side.setblocking(True)
        store_side.sendall(sent)
        if how == "reset":  # an RST after what was sent
            store_side.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        await asyncio.sleep(0.05)  # the bytes are in the source's buffer before it ends
        store_side.close()
        with pytest.raises(SourceEnded) as ended:
            await splice_exactly(source.fileno(), destination.fileno(), 1_000_000, stall_s=5)
        moved = ended.value.moved
        assert await read_exactly(client_side, moved) == sent[:moved]
        if how == "closed":
            assert moved == len(sent)  # everything it sent reached the destination
        for sock in (source, destination, client_side):
            sock.close()

    asyncio.run(main())


def test_a_source_that_goes_silent_is_given_up_after_the_stall_timeout():
    async def main() -> None:
        store_side, source = pair()
        destination, client_side = pair()
        store_side.send(b"x" * 1000)
        loop = asyncio.get_running_loop()
        started = loop.time()
        with pytest.raises(SourceEnded, match=r"sent nothing for 0\.3 s") as ended:
            await splice_exactly(source.fileno(), destination.fileno(), 10_000, stall_s=0.3)
        assert ended.value.moved == 1000 and loop.time() - started < 5
        assert await read_exactly(client_side, 1000) == b"x" * 1000
        for sock in (store_side, source, destination, client_side):
            sock.close()

    asyncio.run(main())


def test_a_destination_that_goes_away_ends_the_splice():
    async def main() -> None:
        store_side, source = pair()
        destination, client_side = pair()
        client_side.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
        client_side.close()  # reset: the next write fails
        loop = asyncio.get_running_loop()
        sending = asyncio.create_task(loop.sock_sendall(store_side, os.urandom(4_000_000)))
        with pytest.raises(DestinationFailed):
            await splice_exactly(source.fileno(), destination.fileno(), 4_000_000, stall_s=5)
        sending.cancel()
        for sock in (store_side, source, destination):
            sock.close()

    asyncio.run(main())


def test_an_open_ended_splice_runs_to_the_source_s_end():
    async def main() -> None:
        store_side, source = pair()
        destination, client_side = pair()
        loop = asyncio.get_running_loop()
        ended: asyncio.Future[Ending] = loop.create_future()
        splice = Splice(loop, source.fileno(), destination.fileno(), ended.set_result)
        payload = os.urandom(3_000_000)
        receiving = asyncio.create_task(read_exactly(client_side, len(payload) + 1))
        await loop.sock_sendall(store_side, payload)
        store_side.close()
        assert await ended is Ending.SOURCE_ENDED and splice.closed and splice.moved == len(payload)
        destination.close()  # as the gRPC front closes it after the source's end
        assert await receiving == payload
        for sock in (source, client_side):
            sock.close()

    asyncio.run(main())
