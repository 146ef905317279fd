"""An object of a store read as a seekable file, by ranged reads (`ObjectFile`)."""

from __future__ import annotations

import io
from pathlib import Path

from services.storage.objectstore import ObjectFile, open_store


def test_an_object_reads_as_a_seekable_file(tmp_path: Path) -> None:
    store = open_store(tmp_path.as_uri())
    store.put("x/object", io.BytesIO(b"0123456789"))
    handle = ObjectFile(store, "x/object", 10)
    assert handle.seek(0, io.SEEK_END) == 10
    assert handle.seek(-4, io.SEEK_END) == 6 and handle.read(2) == b"67" and handle.tell() == 8
    assert handle.read() == b"89" and handle.read(5) == b""
    handle.seek(1)
    assert handle.read(3) == b"123"
