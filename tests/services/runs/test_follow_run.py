"""`follow_run`, in process: a live run's stream carries what is appended while it is followed, is
byte for byte the download of the finished run, ends with a footer when the run ends, and a viewer
that goes away leaves no open file or waiter behind."""

from __future__ import annotations

import asyncio
import io
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from services.hot import read
from services.hot.read import HotRecording
from services.hot.store import HotRun, HotStore
from services.rrd import ArrowMessage, iter_events
from services.rrd.decoder import RrdDecoder
from services.rrd.footer import read_footer
from services.rrd.frames import MessageKind
from services.rrd.messages import BlueprintActivationMessage, StoreInfoMessage, StreamStart
from services.runs import download
from services.runs.download import EntityFilter, follow_run
from tests.services.rrd.recordings import Recording
from tests.services.runs.decoded import stream_run

pytestmark = pytest.mark.sdk
WAKE_S = 5.0


@pytest.fixture(autouse=True)
def no_recheck(monkeypatch: pytest.MonkeyPatch) -> None:
    """Only a notification can wake a follower in these tests."""
    monkeypatch.setattr(read, "FOLLOW_RECHECK_S", 3600.0)


class LiveRun:
    """A hot run written from a recording's messages, and its live flag, as ingest shows them."""

    def __init__(self, hot_store: HotStore, rec: Recording) -> None:
        events = list(iter_events(rec.path))
        version = next(e.version for e in events if isinstance(e, StreamStart))
        self.messages = [
            (_kind(e), e.raw)
            for e in events
            if isinstance(e, StoreInfoMessage | ArrowMessage | BlueprintActivationMessage)
        ]
        self.hot: HotRun = hot_store.create("followed", version)
        self.live = True

    def write(self, start: int, end: int) -> None:
        for kind, raw in self.messages[start:end]:
            self.hot.append(kind, raw)

    def recording(self) -> HotRecording:
        return HotRecording(self.hot.path, self.hot.size, {}, lambda: (self.hot.size, self.live), self.hot.changes)

    def end(self) -> None:
        self.live = False
        self.hot.changes.notify()


def _kind(event: StoreInfoMessage | ArrowMessage | BlueprintActivationMessage) -> MessageKind:
    if isinstance(event, StoreInfoMessage):
        return MessageKind.SET_STORE_INFO
    return MessageKind.ARROW_MSG if isinstance(event, ArrowMessage) else MessageKind.BLUEPRINT_ACTIVATION


def chunk_ids(data: bytes) -> list[bytes]:
    """The chunks in `data`, which may be a stream cut after any whole message."""
    return [e.chunk_id or b"" for e in RrdDecoder().feed(data) if isinstance(e, ArrowMessage)]


async def next_piece(body: AsyncIterator[bytes]) -> bytes:
    return await asyncio.wait_for(anext(body), WAKE_S)


@pytest.mark.parametrize("on_loop_bytes", [0, 1 << 30], ids=["read-on-a-thread", "read-on-the-loop"])
@pytest.mark.parametrize("entities", [EntityFilter(), EntityFilter(include=["/world/points"])], ids=["all", "one"])
def test_a_followed_run_is_the_download_of_the_finished_run(
    hot_store: HotStore,
    recordings: dict[str, Recording],
    monkeypatch: pytest.MonkeyPatch,
    on_loop_bytes: int,
    entities: EntityFilter,
):
    monkeypatch.setattr(download, "ON_LOOP_BYTES", on_loop_bytes)
    run = LiveRun(hot_store, recordings["points"])
    half = len(run.messages) // 2
    run.write(0, half)

    async def scenario() -> bytes:
        body = follow_run(run.recording(), entities)
        received = bytearray(await next_piece(body))  # the run so far, sent before waiting
        so_far = chunk_ids(bytes(received))
        assert so_far
        waiting = asyncio.create_task(next_piece(body))
        while run.hot.changes.waiting == 0:  # the follower waits for the run
            await asyncio.sleep(0)
        run.write(half, len(run.messages))
        received += await waiting
        assert len(chunk_ids(bytes(received))) > len(so_far)  # chunks written while it was followed
        run.end()
        async for piece in body:
            received += piece
        return bytes(received)

    followed = asyncio.run(scenario())
    finished = b"".join(stream_run(run.hot.path, run.hot.size, entities))
    assert followed == finished
    assert read_footer(io.BytesIO(followed)) is not None


def test_a_viewer_that_goes_away_leaves_no_open_file_or_waiter(hot_store: HotStore, recordings: dict[str, Recording]):
    run = LiveRun(hot_store, recordings["points"])
    run.write(0, len(run.messages))
    writer_only = _open_on(run.hot.path)  # the hot tier's own descriptor

    async def scenario() -> None:
        body = follow_run(run.recording(), EntityFilter())
        assert await next_piece(body)
        assert _open_on(run.hot.path) == writer_only + 1  # the follower's reader

        async def rest() -> None:
            async for _ in body:
                pass

        follower = asyncio.create_task(rest())
        while run.hot.changes.waiting == 0:
            await asyncio.sleep(0)
        follower.cancel()  # what the server does when the connection drops
        with pytest.raises(asyncio.CancelledError):
            await follower
        assert run.hot.changes.waiting == 0

    asyncio.run(scenario())
    assert _open_on(run.hot.path) == writer_only


def _open_on(path: Path) -> int:
    """How many of this process's file descriptors are open on `path` (Linux)."""
    return sum(1 for fd in Path("/proc/self/fd").iterdir() if fd.resolve() == path.resolve())
