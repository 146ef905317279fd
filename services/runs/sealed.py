"""Serving a sealed run (warm, or cold once restored) with ranged reads planned from its chunk index.

An unfiltered download is the sealed object itself, copied through (several ranges read at once:
`services.storage.readahead`); any other is planned from
`chunks.parquet` like a hot run's from its index (`services.runs.indexed`), reading only the
messages it keeps.
"""

from __future__ import annotations

from collections.abc import Iterator

from services.runs.download import FLUSH_BYTES, EntityFilter, TimeWindow
from services.runs.indexed import IndexedRecording, open_sealed_object, stream_indexed
from services.sealed.read import SealedRecording
from services.storage.readahead import pieces, read_ahead


def indexed_recording(sealed: SealedRecording) -> IndexedRecording:
    """The sealed object read by range from the warm store, with the chunk index already read."""
    return open_sealed_object(sealed.store, sealed.key, sealed.size, lambda: sealed.rows)


def whole_object(entities: EntityFilter, blueprint: bool, window: TimeWindow | None) -> bool:
    """Whether the download is the sealed object itself (nothing filtered out)."""
    return not entities.include and not entities.exclude and blueprint and window is None


def stream_sealed(
    sealed: SealedRecording, entities: EntityFilter, *, blueprint: bool = True, window: TimeWindow | None = None
) -> Iterator[bytes | memoryview]:
    if whole_object(entities, blueprint, window):
        # The sealed object is already the answer: read by ranges, several under way at once.
        def read(piece: tuple[int, int]) -> bytes:
            return sealed.store.get_range(sealed.key, *piece)

        for _, data in read_ahead(pieces(0, sealed.size, first=FLUSH_BYTES), read):
            yield data
        return
    yield from stream_indexed(indexed_recording(sealed), entities, blueprint=blueprint, window=window)
