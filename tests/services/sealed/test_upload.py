"""A run sealed straight into the store: the object is the sealed recording byte for byte (its
SHA-256 and size as the sealing counted them), no local copy is made, and a sealing that fails, or an
upload that fails, leaves the object that was there before."""

from __future__ import annotations

import datetime as dt
import hashlib
import io
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import pytest

from services.rrd import iter_events
from services.rrd.messages import ArrowMessage, Event
from services.sealed.upload import seal_to_store
from services.sealed.write import seal
from services.storage.local import LocalStore
from services.storage.objectstore import ObjectInfo, StorageError
from services.storage.pipe import WRITE_PIECE
from tests.services.retention.conftest import log_run

NOW = dt.datetime(2026, 11, 30, 12, tzinfo=dt.UTC)
KEY = "robot/2026-11-30/run-1/recording.rrd"


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return log_run(
        tmp_path_factory.mktemp("run") / "run.rrd", "run-1", entities=3, frames=20, points=10_000, chunk_rows=1
    )


def test_the_stored_object_is_the_sealed_recording(recording: Path, tmp_path: Path) -> None:
    store = LocalStore((tmp_path / "warm").as_uri())
    sealed = seal_to_store(store, KEY, [iter(iter_events(recording))], "run-1", NOW)
    info = store.head(KEY)
    local = io.BytesIO()
    again = seal([iter(iter_events(recording))], local, "run-1", NOW)  # the same sealing into memory
    stored = store.get_range(KEY)
    assert stored == local.getvalue() and info.size == len(stored) == sealed.recording_size > 100_000
    assert sealed.recording_sha256 == hashlib.sha256(stored).hexdigest() == again.recording_sha256
    assert [p.name for p in (tmp_path / "warm").rglob("*") if p.is_file()] == ["recording.rrd"]  # nothing else


def test_a_sealing_that_fails_leaves_the_object_as_it_was(recording: Path, tmp_path: Path) -> None:
    store = LocalStore((tmp_path / "warm").as_uri())
    store.put(KEY, b"the sealed run before")

    def breaks_midway() -> Iterator[Event]:
        for n, event in enumerate(iter_events(recording)):
            if n == 40 and isinstance(event, ArrowMessage):
                raise OSError("hot disk read error")
            yield event

    with pytest.raises(OSError, match="hot disk read error"):
        seal_to_store(store, KEY, [breaks_midway()], "run-1", NOW)
    assert store.get_range(KEY) == b"the sealed run before"
    assert [p.name for p in (tmp_path / "warm").rglob("*") if p.is_file()] == ["recording.rrd"]  # no leftovers


def test_an_upload_that_fails_stops_the_sealing(recording: Path, tmp_path: Path) -> None:
    store = LocalStore((tmp_path / "warm").as_uri())
    read: list[int] = []

    class FailingStore(LocalStore):
        def put(self, key: str, data: bytes | BinaryIO) -> ObjectInfo:
            assert not isinstance(data, bytes)
            read.append(len(data.read(1024)))
            raise StorageError("the store went away")

    events_read = 0

    def counted() -> Iterator[Event]:
        nonlocal events_read
        for event in iter_events(recording):
            events_read += 1
            yield event

    failing = FailingStore(store.url)
    with pytest.raises(StorageError, match="went away"):
        seal_to_store(failing, KEY, [counted()], "run-1", NOW, pipe_bytes=WRITE_PIECE)
    total = sum(1 for _ in iter_events(recording))
    assert read == [1024] and events_read < total  # the sealing stopped when the upload gave up
