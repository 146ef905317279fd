"""WriteMessages served by the front (`h2_writes`) within bounds: back-pressure, keepalive, memory
a client can make the server hold, clients that read nothing, and stopping."""

from __future__ import annotations

import asyncio
import contextlib
import time
import tracemalloc
from collections.abc import AsyncIterator
from typing import Any

import grpc
import pytest
from hpack import Encoder

from tests.services.api.h2_client import (
    ACK,
    DATA,
    END_HEADERS,
    END_STREAM,
    HEADERS,
    PING,
    Got,
    Handler,
    Reply,
    asynchronous,
    connected,
    frame,
    message,
    raw_first,
    read_all,
    request,
    roundtrip,
    send_until_stalled,
    send_until_stalled_or_closed,
)


@asynchronous
async def test_keepalive_pings_a_silent_client_and_closes_one_that_does_not_answer(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr("services.api.h2_writes.KEEPALIVE_S", 0.15)
    monkeypatch.setattr("services.api.h2_writes.KEEPALIVE_TIMEOUT_S", 0.3)
    handler, started = Handler(), time.monotonic()
    async with connected(handler, raw_first(Encoder())) as (_, client):

        def pings() -> list[bytes]:
            return [payload for flags, _, payload in client.of(PING) if not flags & ACK]

        await client.until(pings)
        assert time.monotonic() - started >= 0.15 - 0.02 and len(pings()[0]) == 8
        await client.send(frame(PING, ACK, 0, pings()[0]))  # answered: pinged again later, not closed
        await client.until(lambda: len(pings()) == 2)
        second_ping = time.monotonic()
        await client.until(lambda: client.closed)  # not answered: closed, not before the timeout
        assert time.monotonic() - second_ping >= 0.3 - 0.05
        await handler.wait(lambda: "s1" in handler.finished)
        assert handler.ended["s1"] == "CancelledError"


@asynchronous
async def test_a_handler_that_does_not_read_stops_the_connection_reading(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr("services.api.h2_writes.QUEUE_LIMIT", 256 << 10)
    bodies = [bytes([i % 256]) * (100_000, 1_000, 30_000)[i % 3] for i in range(180)]  # 7.9 MB
    stream = b"".join(message(body) for body in bodies)
    data = b"".join(frame(DATA, 0, 1, stream[i : i + 250_000]) for i in range(0, len(stream), 250_000))
    go = asyncio.Event()

    async def read_when_told(requests: AsyncIterator[bytes], call: Any, got: Got) -> bytes:
        await go.wait()
        while (request := await call.read()) is not grpc.aio.EOF:
            got.append(request)
        return b"read"

    handler = Handler(read_when_told)
    async with connected(handler, raw_first(Encoder()), buffer=64 << 10) as (_, client):
        sent = await send_until_stalled(client.sock, data, stall=0.3)
        # what the server read: its queue limit, a read buffer and the kernel's buffers, no more
        assert sent < 2_500_000 and handler.received["s1"] == []
        go.set()
        await client.send(data[sent:] + frame(DATA, END_STREAM, 1))
        assert await client.answered(1) == 0 and client.answer(1) == message(b"read")
        assert handler.received["s1"] == bodies


@asynchronous
async def test_what_a_refused_stream_held_unread_is_released(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr("services.api.h2_writes.QUEUE_LIMIT", 64 << 10)
    encoder = Encoder()  # stream 1's 100 kB are all queued when the hand-over feeds them, before it is refused
    first = raw_first(encoder) + frame(DATA, 0, 1, b"".join(message(bytes(20_000)) for _ in range(5)))

    async def refuse(requests: AsyncIterator[bytes], call: Any, got: Got) -> None:
        await call.abort(grpc.StatusCode.UNAUTHENTICATED, "no token")

    handler = Handler(refuse)
    async with connected(handler, first) as (_, client):
        assert await client.answered(1) == grpc.StatusCode.UNAUTHENTICATED.value[0]
        handler.serve = read_all
        request3 = encoder.encode(request("s3"))
        await client.send(frame(HEADERS, END_HEADERS, 3, request3) + frame(DATA, END_STREAM, 3, message(b"again")))
        assert await client.answered(3, timeout=2) == 0 and handler.received["s3"] == [b"again"]


@asynchronous
async def test_a_declared_message_length_is_not_allocated_before_its_bytes_come():
    """A message's 5-byte prefix names its length. Were its buffer allocated whole from that, a few
    hundred bytes from a client (100 streams, each declaring FLEET_MAX_MESSAGE_SIZE) would make the
    server allocate gigabytes: what is allocated ahead of the bytes is bounded per connection."""
    declared, streams = 16 << 20, 8
    tracemalloc.start()
    try:
        async with connected(Handler(), max_message=declared) as (_, client):
            before = tracemalloc.get_traced_memory()[0]
            for i in range(streams):
                stream = 1 + 2 * i
                if stream != 1:
                    client.conn.send_headers(stream, request(f"s{stream}"))
                await client.data(stream, (0).to_bytes(1, "big") + declared.to_bytes(4, "big") + b"xyz")
            await roundtrip(client)
            grown = tracemalloc.get_traced_memory()[0] - before
            assert grown < 32 << 20, f"{grown >> 20} MiB held for {streams * 8} bytes of message"
    finally:
        tracemalloc.stop()


@asynchronous
async def test_pings_from_a_client_that_reads_nothing_do_not_pile_up_in_the_server():
    """Every PING (and SETTINGS, and refused HEADERS) is answered with a write; from a client that
    sends them and reads nothing, the server stops reading once its answers fill the transport's
    write buffer, instead of buffering them without limit."""
    handler = Handler()
    pings = b"".join(frame(PING, 0, 0, i.to_bytes(8, "big")) for i in range(150_000))  # 2.5 MB
    async with connected(handler, raw_first(Encoder()), buffer=32 << 10, back_buffer=32 << 10) as (_, client):
        sent = await send_until_stalled_or_closed(client.sock, pings, stall=0.5)
        assert sent < len(pings)


@asynchronous
async def test_stop_ends_a_connection_whose_client_reads_nothing():
    """`WriteServer.stop` cancels the handlers at once and aborts a transport whose client reads
    nothing (closing it would wait for its unsent bytes for ever)."""
    handler = Handler()
    pings = b"".join(frame(PING, 0, 0, i.to_bytes(8, "big")) for i in range(30_000))  # 510 kB
    async with connected(handler, raw_first(Encoder()), buffer=32 << 10, back_buffer=32 << 10) as (server, client):
        await send_until_stalled_or_closed(client.sock, pings, stall=0.5)
        await asyncio.wait_for(server.stop(), 2)
        assert handler.ended["s1"] == "CancelledError"


@asynchronous
async def test_keepalive_does_not_close_a_connection_that_back_pressure_paused(monkeypatch: pytest.MonkeyPatch):
    """While reading is paused (a handler slow to take what came), nothing is read, the client's
    answers to pings included: the keepalive does not take that silence for a dead client."""
    monkeypatch.setattr("services.api.h2_writes.QUEUE_LIMIT", 64 << 10)
    monkeypatch.setattr("services.api.h2_writes.KEEPALIVE_S", 0.4)
    monkeypatch.setattr("services.api.h2_writes.KEEPALIVE_TIMEOUT_S", 0.6)
    bodies = [bytes([i]) * 20_000 for i in range(100)]  # 2 MB
    stream = b"".join(message(body) for body in bodies)
    data = b"".join(frame(DATA, 0, 1, stream[i : i + 250_000]) for i in range(0, len(stream), 250_000))
    go = asyncio.Event()

    async def read_when_told(requests: AsyncIterator[bytes], call: Any, got: Got) -> Any:
        await go.wait()
        while (request := await call.read()) is not grpc.aio.EOF:
            got.append(request)
        return Reply()

    handler = Handler(read_when_told)
    async with connected(handler, raw_first(Encoder()), buffer=64 << 10) as (_, client):
        sent = await send_until_stalled(client.sock, data, stall=0.2)
        assert sent < len(data)  # paused

        def pings() -> list[bytes]:
            return [payload for flags, _, payload in client.of(PING) if not flags & ACK]

        await client.until(pings)  # the server pings the client it does not read (no answer can
        # come while the client is in the middle of a frame; none could be read anyway),
        with pytest.raises(TimeoutError):  # and does not close it for that (twice the timeout's time)
            await client.until(lambda: False, timeout=1.2)
        go.set()
        await client.send(data[sent:] + frame(DATA, END_STREAM, 1))
        assert await client.answered(1) == 0 and handler.received["s1"] == bodies


@asynchronous
async def test_a_stream_whose_handler_does_not_read_leaves_the_other_streams_flowing():
    """Flow control is per stream in HTTP/2 and gRPC: a stream whose handler does not read stops
    within its window, and the connection's other streams go on (a stream's window comes back as its
    handler takes what it was sent, not as it is parsed)."""
    go = asyncio.Event()

    async def first_slow(requests: AsyncIterator[bytes], call: Any, got: Got) -> Any:
        if dict(call.invocation_metadata())["x-name"] == "s1":
            await go.wait()
        return await read_all(requests, call, got)

    handler = Handler(first_slow)
    stream = b"".join(message(bytes([i % 256]) * 60_000) for i in range(700))  # 42 MB
    async with connected(handler) as (_, client):
        loop, sent = asyncio.get_running_loop(), 0
        deadline = loop.time() + 2.0
        while sent < len(stream) and loop.time() < deadline:  # within the windows the server gives
            room = min(client.conn.local_flow_control_window(1), 1 << 20, len(stream) - sent)
            if room:
                await client.data(1, stream[sent : sent + room])
                sent += room
            else:
                with contextlib.suppress(TimeoutError):
                    await client.until(lambda: client.conn.local_flow_control_window(1) > 0, timeout=0.2)
        assert sent < len(stream)  # stream 1 stopped, as it should
        client.conn.send_headers(3, request("s3"))
        await client.data(3, message(b"other stream"), end=True)
        try:
            assert await client.answered(3, timeout=2) == 0 and handler.received["s3"] == [b"other stream"]
        finally:
            go.set()
