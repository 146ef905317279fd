"""A whole sealed run streamed from its store (`services.runs.sealed.stream_resumed`): a stream that
breaks off is taken up again where it stopped, and given up after a few breaks."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from services.runs.sealed import STREAM_ATTEMPTS, stream_resumed
from services.storage.objectstore import StorageError

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
