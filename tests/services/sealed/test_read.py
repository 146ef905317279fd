"""A sealed recording's chunk index (services/sealed/read.py): read on first use only, and parsed
once for the windows asked of one recording, again once the recording is sealed anew."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from pathlib import Path

from services.rrd.chunk_index import IndexRow
from services.sealed.index import to_parquet
from services.sealed.read import open_sealed
from services.sealed.write import INDEX, RECORDING
from services.storage.objectstore import ObjectInfo, open_store
from tests.services.storage.counting import CountingStore

PREFIX = "robot-7/2026-11-30/run-cache"


def _seal(store: CountingStore, recording: bytes, chunks: int) -> None:
    rows = [IndexRow("chunk", "recording", 100 * i, 100, i.to_bytes(16, "big"), "/a") for i in range(chunks)]
    store.put(f"{PREFIX}/{RECORDING}", recording)
    store.put(f"{PREFIX}/{INDEX}", to_parquet(rows))


def _index_reads(store: CountingStore) -> int:
    return sum(1 for read in store.reads if read.key.endswith(INDEX))


def test_the_index_is_read_when_asked_for_and_parsed_once_per_recording(tmp_path: Path):
    store = CountingStore(open_store((tmp_path / "warm").as_uri()))
    _seal(store, b"x" * 1000, chunks=3)
    first = open_sealed(store, PREFIX)
    assert _index_reads(store) == 0  # opening needs the recording's size, not its index
    assert len(first.rows) == 3 and _index_reads(store) == 1
    again = open_sealed(store, PREFIX)
    assert again.rows == first.rows and _index_reads(store) == 1  # a second window: no new parse

    _seal(store, b"y" * 1000, chunks=5)  # sealed anew (same size): a new version of the recording
    assert len(open_sealed(store, PREFIX).rows) == 5 and _index_reads(store) == 2


@dataclass
class WatchedStore(CountingStore):
    """A store whose HEAD waits, while `head_waits`, until the index's read has begun (10 s at most),
    and records whether it had."""

    head_waits: bool = True
    index_asked: threading.Event = field(default_factory=threading.Event)
    overlapped: list[bool] = field(default_factory=list)

    def get_range(self, key: str, start: int = 0, length: int | None = None) -> bytes:
        if key.endswith(INDEX):
            self.index_asked.set()
        return super().get_range(key, start, length)

    def head(self, key: str) -> ObjectInfo:
        self.overlapped.append(self.index_asked.wait(10) if self.head_waits else self.index_asked.is_set())
        return super().head(key)


def test_an_index_a_window_will_need_is_read_while_the_recording_is_looked_at(tmp_path: Path):
    store = WatchedStore(open_store((tmp_path / "warm").as_uri()))
    _seal(store, b"x" * 1000, chunks=3)
    first = open_sealed(store, PREFIX, index=True)
    assert store.overlapped == [True]  # asked for before the HEAD answered
    assert len(first.rows) == 3 and _index_reads(store) == 1  # and that read is the one parsed
    store.head_waits, store.index_asked = False, threading.Event()
    again = open_sealed(store, PREFIX, index=True)  # parsed already: not read again
    assert again.rows == first.rows and _index_reads(store) == 1 and store.overlapped == [True, False]
