"""Serving a sealed run (warm, or cold once restored) with ranged reads planned from its chunk index.

An unfiltered download is the sealed object itself, copied through: one GET read on the event loop
where the store allows it (S3: `loop_read`), else one GET stream read a few pieces ahead of the
sender in a thread, else several ranges read at once (`services.storage.readahead`); any other is
planned from
`chunks.parquet` like a hot run's from its index (`services.runs.indexed`), reading only the
messages it keeps.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable, Iterator

from services.runs.download import FLUSH_BYTES, EntityFilter, TimeWindow
from services.runs.indexed import IndexedRecording, open_sealed_object, stream_indexed
from services.sealed.read import SealedRecording
from services.storage.objectstore import (
    LoopReadingStore,
    StorageError,
    StreamingStore,
    supports_loop_reads,
    supports_streaming,
)
from services.storage.readahead import pieces, read_ahead, stream_ahead
from services.storage.splice import Source, SourceEnded


def indexed_recording(sealed: SealedRecording) -> IndexedRecording:
    """The sealed object read by range from the warm store, with its chunk index (read on first use,
    its rows made as they are needed)."""
    return open_sealed_object(sealed.store, sealed.key, sealed.size, lambda: sealed.index)


def whole_object(entities: EntityFilter, blueprint: bool, window: TimeWindow | None) -> bool:
    """Whether the download is the sealed object itself (nothing filtered out)."""
    return not entities.include and not entities.exclude and blueprint and window is None


STREAM_ATTEMPTS = 3  # a stream that breaks off is taken up again where it stopped, this many times


def stream_resumed(store: StreamingStore, key: str, size: int) -> Iterator[bytes]:
    """The object's bytes by one stream, opened again from where it stopped if it breaks off (a
    store's connection reset mid-way does not cut a download short)."""
    offset, failures = 0, 0
    while offset < size:
        try:
            for piece in store.stream(key, offset, size - offset):
                offset += len(piece)
                yield piece
            if offset < size:
                raise StorageError(f"{key!r} ended after {offset} of {size} bytes")
        except StorageError:
            failures += 1
            if failures >= STREAM_ATTEMPTS:
                raise


async def loop_resumed(store: LoopReadingStore, key: str, size: int) -> AsyncIterator[memoryview]:
    """As `stream_resumed`, read on the event loop."""
    offset, failures = 0, 0
    while offset < size:
        try:
            async for piece in store.loop_read(key, offset, size - offset):
                offset += len(piece)
                yield piece
            if offset < size:
                raise StorageError(f"{key!r} ended after {offset} of {size} bytes")
        except StorageError:
            failures += 1
            if failures >= STREAM_ATTEMPTS:
                raise


class WholeOnLoop(AsyncIterator[memoryview]):
    """The sealed object itself, read on the event loop: iterated, its pieces as they arrive
    (`loop_resumed`), or, where the store's answers can be handed over, moved by the kernel from the
    store's socket to the client's (`send_by_splice`, which a server offering it calls)."""

    def __init__(self, store: LoopReadingStore, key: str, size: int) -> None:
        self.store, self.key, self.size = store, key, size
        self._pieces: AsyncIterator[memoryview] | None = None

    async def __anext__(self) -> memoryview:
        if self._pieces is None:
            self._pieces = loop_resumed(self.store, self.key, self.size)
        return await anext(self._pieces)

    def splices(self) -> bool:
        return self.store.loop_splices()

    async def send_by_splice(
        self, write: Callable[[bytes], Awaitable[None]], splice: Callable[[Source], Awaitable[None]]
    ) -> None:
        """The object sent with `write` (the bytes that came with a GET's head) and `splice` (the
        rest of that GET's body; raises SourceEnded naming what it moved), a GET that breaks off
        taken up again where it stopped, as `loop_resumed` does."""
        offset, failures = 0, 0
        while offset < self.size:
            try:
                async with self.store.loop_open(self.key, offset, self.size - offset) as source:
                    if source.leading:
                        await write(source.leading)
                        offset += len(source.leading)
                    try:
                        await splice(source)
                    except SourceEnded as exc:
                        offset += exc.moved
                        raise StorageError(
                            f"{self.key!r} broke off after {offset} of {self.size} bytes: {exc}"
                        ) from exc
                    offset += source.left
            except StorageError:
                failures += 1
                if failures >= STREAM_ATTEMPTS:
                    raise


def whole_on_loop(sealed: SealedRecording) -> WholeOnLoop | None:
    """The sealed object itself, read on the event loop, where its store allows it (else None)."""
    store = sealed.store
    return WholeOnLoop(store, sealed.key, sealed.size) if supports_loop_reads(store) else None


def stream_sealed(
    sealed: SealedRecording, entities: EntityFilter, *, blueprint: bool = True, window: TimeWindow | None = None
) -> Iterator[bytes | memoryview]:
    if whole_object(entities, blueprint, window):
        # The sealed object is already the answer.
        if supports_streaming(sealed.store):
            yield from stream_ahead(stream_resumed(sealed.store, sealed.key, sealed.size))
            return

        def read(piece: tuple[int, int]) -> bytes:
            return sealed.store.get_range(sealed.key, *piece)

        for _, data in read_ahead(pieces(0, sealed.size, first=FLUSH_BYTES), read):
            yield data
        return
    yield from stream_indexed(indexed_recording(sealed), entities, blueprint=blueprint, window=window)
