"""One GET read on the event loop (`services.storage.loop_get`, `S3Store.loop_read`): the object as a
real S3 server sends it, from any offset; what a store may answer instead (refusals, a cut, a stall,
a head that never ends), each one clear error that names the object and never the signed URL; and
at most `depth` pieces held while the sender is behind."""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import AsyncGenerator, AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path
from typing import cast

import pytest

from core.errors import ConflictError
from services.storage import loop_get
from services.storage.objectstore import (
    STREAM_PIECE_BYTES,
    ObjectNotFoundError,
    StorageError,
    open_store,
    supports_loop_reads,
)
from services.storage.s3 import S3Store
from tests.services.storage.s3_backends import BUCKET, REGION

SECRET_QUERY = "X-Amz-Signature=feedface"
Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


def read_all(url: str, start: int, length: int, reading: loop_get.Reading) -> list[bytes]:
    async def main() -> list[bytes]:
        return [bytes(piece) async for piece in loop_get.get(url, start, length, reading)]

    return asyncio.run(main())


def served(handler: Handler, start: int, length: int, **reading: float) -> list[bytes]:
    """What `loop_get.get` reads from a scripted server on loopback answering with `handler`."""

    async def main() -> list[bytes]:
        server = await asyncio.start_server(handler, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        try:
            what = loop_get.Reading("'r/recording.rrd' from s3://b/p", piece=1000, depth=2, **reading)  # type: ignore[arg-type]
            url = f"http://127.0.0.1:{port}/b/p/r/recording.rrd?{SECRET_QUERY}"
            return [bytes(piece) async for piece in loop_get.get(url, start, length, what)]
        finally:
            server.close()

    return asyncio.run(main())


def answering(head: bytes, body: bytes = b"", *, then: str = "close") -> Handler:
    """A server that reads the request, sends `head` and `body`, then closes (or stalls)."""

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await reader.readuntil(b"\r\n\r\n")
        writer.write(head + body)
        await writer.drain()
        if then == "stall":
            await asyncio.sleep(30)  # longer than the reader waits: it gives up first
        writer.close()

    return handle


DATA = os.urandom(5000)
DENIED = b"<Error><Code>AccessDenied</Code><Message>no</Message></Error>"


def ok(body: bytes, extra: bytes = b"") -> bytes:
    return b"HTTP/1.1 200 OK\r\nContent-Length: %d\r\n%s\r\n" % (len(body), extra)


def sent_through(handler: Handler, length: int, piece_bytes: int, *, keep_views: bool) -> tuple[bytes, int]:
    """The body as a sender gets it that holds on to every piece as given (`keep_views`: a view of
    the reader's buffer, as a transport keeps what it could not send yet) or copies each and lets
    it go; and how many distinct buffers the pieces came in."""

    async def main() -> tuple[bytes, int]:
        server = await asyncio.start_server(handler, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        kept: list[bytes | memoryview] = []
        buffers: dict[int, object] = {}  # the buffers themselves (not views: holding them pins nothing)
        try:
            what = loop_get.Reading("'r/recording.rrd' from s3://b/p", piece=piece_bytes, depth=2)
            async for piece in loop_get.get(f"http://127.0.0.1:{port}/b/p/r/recording.rrd", 0, length, what):
                buffers[id(piece.obj)] = piece.obj
                kept.append(piece if keep_views else bytes(piece))
        finally:
            server.close()
        return b"".join(kept), len(buffers)

    return asyncio.run(main())


def test_buffers_of_pieces_sent_are_filled_again_and_never_one_still_viewed():
    body, piece = os.urandom(2_000_000), 20_000
    data, buffers = sent_through(answering(ok(body), body), len(body), piece, keep_views=False)
    # The body's first bytes may come with the head (up to HEAD_LIMIT), cut into pieces at once;
    # from then on: `depth` waiting, LENT_SPARE with the sender, the one being filled.
    with_the_head = -(-loop_get.HEAD_LIMIT // piece)
    assert data == body and buffers <= with_the_head + 2 + loop_get.LENT_SPARE + 1, buffers
    data, buffers = sent_through(answering(ok(body), body), len(body), piece, keep_views=True)
    assert data == body and buffers == len(body) // piece  # every piece still viewed: none written over


def test_the_body_arrives_whole_in_pieces_of_the_reading_size():
    pieces = served(answering(ok(DATA), DATA), 0, len(DATA))
    assert b"".join(pieces) == DATA and max(len(p) for p in pieces) <= 1000


def test_a_range_is_asked_from_the_offset_and_its_answer_checked():
    asked: list[bytes] = []

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        asked.append(await reader.readuntil(b"\r\n\r\n"))
        tail = DATA[1234:]
        writer.write(
            b"HTTP/1.1 206 Partial Content\r\nContent-Length: %d\r\nContent-Range: bytes 1234-4999/5000\r\n\r\n%s"
            % (len(tail), tail)
        )
        await writer.drain()
        writer.close()

    assert b"".join(served(handle, 1234, len(DATA) - 1234)) == DATA[1234:]
    assert b"\r\nRange: bytes=1234-\r\n" in asked[0] and SECRET_QUERY.encode() in asked[0]


@pytest.mark.parametrize(
    ("head", "error", "message"),
    [
        (b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\n\r\n", ObjectNotFoundError, "no object 'r/recording.rrd'"),
        (
            b"HTTP/1.1 403 Forbidden\r\nContent-Length: %d\r\n\r\n%s" % (len(DENIED), DENIED),
            StorageError,
            "answered HTTP 403 AccessDenied",
        ),
        (
            b"HTTP/1.1 403 Forbidden\r\n\r\n<Error><Code>InvalidObjectState</Code></Error>",
            ConflictError,
            "is archived: restore it before reading",
        ),
        (b"HTTP/1.1 200 OK\r\nTransfer-Encoding: chunked\r\n\r\n", StorageError, "sent no Content-Length"),
        (b"HTTP/1.1 200 OK\r\nContent-Length: 4000\r\n\r\n", StorageError, "the object is not the one the catalog"),
        (b"SSH-2.0-OpenSSH\r\n\r\n", StorageError, "not HTTP/1.1"),
        (b"HTTP/1.1 200 OK\r\nX: " + b"a" * 70_000, StorageError, "head is over 64 KiB"),
        (ok(DATA), StorageError, r"broke off after 0 of 5000 bytes"),
    ],
    ids=["missing", "denied", "archived", "chunked", "other-size", "not-http", "endless-head", "cut"],
)
def test_an_answer_that_is_not_the_object_is_one_clear_error(head: bytes, error: type[Exception], message: str):
    with pytest.raises(error, match=message) as raised:
        served(answering(head), 0, len(DATA))
    assert "recording.rrd" in str(raised.value) and "Signature" not in str(raised.value)


def test_a_body_cut_midway_names_where_it_stopped():
    with pytest.raises(StorageError, match="broke off after 3000 of 5000 bytes"):
        served(answering(ok(DATA), DATA[:3000]), 0, len(DATA))


def test_a_store_that_stops_sending_is_given_up_after_the_read_timeout():
    with pytest.raises(StorageError, match=r"sent nothing for 0\.2 s"):
        served(answering(ok(DATA), DATA[:1000], then="stall"), 0, len(DATA), read_timeout_s=0.2)


def test_a_store_that_cannot_be_reached_is_a_storage_error():
    import socket

    with socket.socket() as closed:  # a port nothing listens on
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    reading = loop_get.Reading("'k' from s3://b")
    with pytest.raises(StorageError, match="'k' from s3://b: cannot reach the store"):
        read_all(f"http://127.0.0.1:{port}/b/k?{SECRET_QUERY}", 0, 10, reading)


class RecordingTransport(asyncio.Transport):
    def __init__(self) -> None:
        super().__init__()
        self.paused = 0
        self.resumed = 0

    def pause_reading(self) -> None:
        self.paused += 1

    def resume_reading(self) -> None:
        self.resumed += 1

    def close(self) -> None:
        pass


def test_reading_pauses_while_depth_pieces_wait_and_resumes_as_they_are_taken():
    """A download holds at most `depth` pieces: the store's socket is not read while they wait."""

    async def main() -> None:
        answer = loop_get._Answer(loop_get.Reading("k", piece=100, depth=3), 0, 1000)
        transport = RecordingTransport()
        answer.connection_made(transport)
        head = b"HTTP/1.1 200 OK\r\nContent-Length: 1000\r\n\r\n"
        answer.get_buffer(-1)[: len(head)] = head
        answer.buffer_updated(len(head))
        for _ in range(3):
            answer.get_buffer(-1)[:100] = b"x" * 100
            answer.buffer_updated(100)
        assert len(answer.ready) == 3 and transport.paused == 1
        assert bytes(await answer.next_piece() or b"") == b"x" * 100
        assert transport.resumed == 1

    asyncio.run(main())


# --- S3Store.loop_read against a real S3 server ------------------------------------------------


@pytest.fixture
def seaweed_store(seaweed_endpoint: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[S3Store]:
    for name, value in (("AWS_ACCESS_KEY_ID", "test"), ("AWS_SECRET_ACCESS_KEY", "test")):
        monkeypatch.setenv(name, value)
    store = open_store(f"s3://{BUCKET}/{tmp_path.name}", endpoint_url=seaweed_endpoint, region=REGION)
    assert supports_loop_reads(store)
    assert isinstance(store, S3Store)
    yield store


async def _collect(pieces: AsyncIterator[memoryview]) -> list[bytes]:
    return [bytes(p) async for p in pieces]


@pytest.mark.s3server
@pytest.mark.slow
def test_a_loop_read_is_the_object_from_any_offset_in_bounded_pieces(seaweed_store: S3Store):
    import io

    data = os.urandom(2 * STREAM_PIECE_BYTES + 54_321)
    seaweed_store.put("r/recording.rrd", io.BytesIO(data))
    whole = asyncio.run(_collect(seaweed_store.loop_read("r/recording.rrd", 0, len(data))))
    assert b"".join(whole) == data and max(len(p) for p in whole) <= STREAM_PIECE_BYTES
    tail = asyncio.run(_collect(seaweed_store.loop_read("r/recording.rrd", 1_000_001, len(data) - 1_000_001)))
    assert b"".join(tail) == data[1_000_001:]
    with pytest.raises(ObjectNotFoundError, match=r"'r/missing\.rrd'") as missing:
        asyncio.run(_collect(seaweed_store.loop_read("r/missing.rrd", 0, 10)))
    assert "Signature" not in str(missing.value)
    with pytest.raises(StorageError, match="not the one the catalog knows"):  # the catalog's size is not the object's
        asyncio.run(_collect(seaweed_store.loop_read("r/recording.rrd", 0, len(data) + 1)))


def test_loop_reads_are_off_behind_a_proxy_or_when_asked(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("AWS_DEFAULT_REGION", REGION)
    for name in ("NO_PROXY", "no_proxy", "HTTPS_PROXY", "https_proxy", "HTTP_PROXY", "http_proxy"):
        monkeypatch.delenv(name, raising=False)
    assert S3Store("s3://b/p", endpoint_url="https://s3.internal:8333").loop_reads
    assert not S3Store("s3://b/p", endpoint_url="https://s3.internal:8333", loop_reads=False).loop_reads
    monkeypatch.setenv("HTTPS_PROXY", "http://proxy.internal:3128")
    assert not S3Store("s3://b/p", endpoint_url="https://s3.internal:8333").loop_reads
    assert not S3Store("s3://b/p").loop_reads  # AWS itself, through the proxy
    monkeypatch.setenv("NO_PROXY", "s3.internal")
    assert S3Store("s3://b/p", endpoint_url="https://s3.internal:8333").loop_reads


def test_a_reader_that_stops_early_closes_the_store_s_connection():
    """A client that goes away mid-download: the GET's socket is closed, not left open to the store."""

    async def main() -> bool:
        closed = asyncio.Event()
        big = b"y" * (8 << 20)

        async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            await reader.readuntil(b"\r\n\r\n")
            writer.write(ok(big))
            try:
                for start in range(0, len(big), 1 << 16):
                    writer.write(big[start : start + (1 << 16)])
                    await writer.drain()  # waits once the reader stops reading; fails once it closes
                await reader.read()  # (or: b"" once the reader's side is closed)
            except ConnectionError:
                pass
            closed.set()
            writer.close()

        server = await asyncio.start_server(handle, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        pieces = cast(
            AsyncGenerator[memoryview, None],
            loop_get.get(f"http://127.0.0.1:{port}/b/k", 0, len(big), loop_get.Reading("'k'")),
        )
        assert len(await anext(pieces)) == 1 << 20
        await pieces.aclose()
        await asyncio.wait_for(closed.wait(), 10)
        server.close()
        return closed.is_set()

    assert asyncio.run(main())


def handed_over(handler: Handler, length: int) -> tuple[bytes, bytes]:
    """What `loop_get.opened` gives for a scripted answer: the bytes that came with the head, and
    the rest as read from the socket it hands over."""

    async def main() -> tuple[bytes, bytes]:
        server = await asyncio.start_server(handler, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        loop = asyncio.get_running_loop()
        try:
            what = loop_get.Reading("'r/recording.rrd' from s3://b/p", read_timeout_s=5)
            url = f"http://127.0.0.1:{port}/b/p/r/recording.rrd?{SECRET_QUERY}"
            async with loop_get.opened(url, 0, length, what) as source:
                assert source.stall_s == what.read_timeout_s  # the store's read timeout, for the splice
                rest = bytearray()
                with socket.socket(fileno=os.dup(source.fd)) as sock:  # read here as a splice would
                    while len(rest) < source.left and (more := await loop.sock_recv(sock, source.left - len(rest))):
                        rest += more
                return source.leading, bytes(rest)
        finally:
            server.close()

    return asyncio.run(main())


def test_an_answer_handed_over_leaves_its_body_in_the_socket_after_what_came_with_the_head():
    def handler(split: int) -> Handler:
        async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            await reader.readuntil(b"\r\n\r\n")
            writer.write(ok(DATA) + DATA[:split])  # the head and the body's first bytes at once
            await writer.drain()
            await asyncio.sleep(0.1)
            writer.write(DATA[split:])
            await writer.drain()
            writer.close()

        return handle

    for split in (0, 1, 4000):
        leading, rest = handed_over(handler(split), len(DATA))
        assert leading == DATA[:split] and leading + rest == DATA


@pytest.mark.parametrize(
    ("head", "error"),
    [(b"HTTP/1.1 404 Not Found\r\n\r\n", ObjectNotFoundError), (ok(DATA[:10]), StorageError)],
    ids=["missing", "other-size"],
)
def test_an_answer_handed_over_is_checked_first(head: bytes, error: type[Exception]):
    with pytest.raises(error) as raised:
        handed_over(answering(head, DATA[:10]), len(DATA))
    assert "recording.rrd" in str(raised.value) and "Signature" not in str(raised.value)


def test_only_a_plain_http_answer_is_handed_over():
    assert loop_get.spliceable("http://127.0.0.1:9000/b/k") and not loop_get.spliceable("https://s3.example/b/k")
    with pytest.raises(StorageError, match="only a plain-HTTP answer"):
        asyncio.run(_open_https())


async def _open_https() -> None:
    async with loop_get.opened("https://s3.example/b/k", 0, 10, loop_get.Reading("k")):
        pass
