"""A local folder as an object store (the embedded default of the warm and cold tiers)."""

from __future__ import annotations

import contextlib
import datetime as dt
import glob
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO
from urllib.parse import urlparse

from services.storage.objectstore import STREAM_PIECE_BYTES, ObjectInfo, ObjectNotFoundError, check_key


class LocalStore:
    def __init__(self, url: str) -> None:
        self.url = url
        self.root = Path(urlparse(url).path)
        self.root.mkdir(parents=True, exist_ok=True)

    def _path(self, key: str) -> Path:
        return self.root / check_key(key)

    def put(self, key: str, data: bytes | BinaryIO) -> ObjectInfo:
        path = self._path(key)
        path.parent.mkdir(parents=True, exist_ok=True)
        # Written beside, synced, then renamed: a reader never sees half an object.
        started = time.time()
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".tmp-{path.name}-")
        try:
            with os.fdopen(fd, "wb") as out:
                if isinstance(data, bytes | bytearray | memoryview):
                    out.write(data)
                else:
                    shutil.copyfileobj(data, out, 8 * 1024 * 1024)
                out.flush()
                os.fsync(out.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        _sweep(path, started)
        return self.head(key)

    def get_range(self, key: str, start: int = 0, length: int | None = None) -> bytes:
        try:
            with open(self._path(key), "rb") as fh:
                fh.seek(start)
                return fh.read() if length is None else fh.read(length)
        except FileNotFoundError:
            raise ObjectNotFoundError(f"no object {key!r} in {self.url}") from None

    def stream(self, key: str, start: int = 0, length: int | None = None) -> Iterator[bytes]:
        try:
            fh = open(self._path(key), "rb")  # noqa: SIM115 (closed when the stream ends or is dropped)
        except FileNotFoundError:
            raise ObjectNotFoundError(f"no object {key!r} in {self.url}") from None
        with fh:
            fh.seek(start)
            left = length
            while left is None or left > 0:
                piece = fh.read(STREAM_PIECE_BYTES if left is None else min(left, STREAM_PIECE_BYTES))
                if not piece:
                    return
                if left is not None:
                    left -= len(piece)
                yield piece

    def head(self, key: str) -> ObjectInfo:
        try:
            stat = self._path(key).stat()
        except FileNotFoundError:
            raise ObjectNotFoundError(f"no object {key!r} in {self.url}") from None
        return ObjectInfo(key, stat.st_size, dt.datetime.fromtimestamp(stat.st_mtime, dt.UTC))

    def list(self, prefix: str = "") -> Iterator[ObjectInfo]:
        keys = []
        for directory, _, files in os.walk(self.root):
            for name in files:
                if name.startswith(".tmp-"):
                    continue
                key = (Path(directory) / name).relative_to(self.root).as_posix()
                if key.startswith(prefix):
                    keys.append(key)
        for key in sorted(keys):
            yield self.head(key)

    def delete(self, key: str) -> None:
        path = self._path(key)
        path.unlink(missing_ok=True)
        _sweep(path)
        for parent in path.parents:  # no empty folders left behind
            if parent == self.root or not parent.is_relative_to(self.root):
                break
            try:
                parent.rmdir()
            except OSError:
                break


def _sweep(path: Path, before: float | None = None) -> None:
    """Remove the temporary files of puts of `path` that never finished (the process was killed
    mid-write): list() does not show them, so nothing else would. With `before`, only those last
    written before then (a put still writing is left alone)."""
    for stale in path.parent.glob(f".tmp-{glob.escape(path.name)}-*"):
        with contextlib.suppress(FileNotFoundError):
            if before is None or stale.stat().st_mtime < before:
                stale.unlink()
