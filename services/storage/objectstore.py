"""The object-store interface and `open_store(url)`, which picks the backend by URL scheme:
`file:///path` (a local folder) or `s3://bucket/prefix` (S3 and S3-compatible servers)."""

from __future__ import annotations

import datetime as dt
import io
import os
import re
from collections.abc import AsyncIterator, Iterator
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass
from typing import BinaryIO, Protocol, TypeGuard
from urllib.parse import urlparse

from core.errors import NotFoundError, UnavailableError
from services.storage.splice import Source

_SAFE_KEY = re.compile(r"^[A-Za-z0-9._\-/=]+$")  # "=": Hive partitions (robot_id=R/)

# A multipart upload holds up to `concurrency` parts of `part_bytes` in memory at once
# (FLEET_S3_PART_BYTES, FLEET_S3_UPLOAD_CONCURRENCY): 64 MiB by default.
PART_BYTES = 16 * 1024 * 1024
UPLOAD_CONCURRENCY = 4


@dataclass(frozen=True)
class Uploads:
    """How a store sends a large object: in parts of `part_bytes`, `concurrency` at once."""

    part_bytes: int = PART_BYTES
    concurrency: int = UPLOAD_CONCURRENCY


class ObjectNotFoundError(NotFoundError):
    """Caught where a missing object is an answer, not a failure (rebuild, archive)."""


class StorageError(UnavailableError):
    """A store that failed: caught where a store outage must not fail the caller (ingest, retention)."""


@dataclass(frozen=True)
class ObjectInfo:
    key: str
    size: int
    last_modified: dt.datetime
    storage_class: str | None = None
    restore: str | None = None  # archived objects: "ongoing" while restoring, "restored" once readable
    etag: str | None = None


class ObjectStore(Protocol):
    url: str

    def put(self, key: str, data: bytes | BinaryIO) -> ObjectInfo:
        """Store `data` (bytes or a binary file read to its end) under `key`, replacing any object."""
        ...

    def get_range(self, key: str, start: int = 0, length: int | None = None) -> bytes:
        """`length` bytes from `start` (to the end when None)."""
        ...

    def head(self, key: str) -> ObjectInfo: ...

    def list(self, prefix: str = "") -> Iterator[ObjectInfo]:
        """Every object whose key starts with `prefix`, in key order."""
        ...

    def delete(self, key: str) -> None:
        """Remove `key`; removing a missing key is not an error (deletes are retried)."""
        ...


class ArchiveStore(ObjectStore, Protocol):
    """A store with archive storage classes (S3): objects move to a class in place and are
    restored for a number of days before they can be read again."""

    def set_storage_class(self, key: str, storage_class: str) -> ObjectInfo: ...

    def restore(self, key: str, days: int) -> None:
        """Ask for a readable copy of an archived object for `days` (it takes time: see head().restore)."""
        ...


def supports_archive(store: ObjectStore) -> bool:
    return hasattr(store, "set_storage_class") and hasattr(store, "restore")


# Pieces of a streamed read (`StreamingStore.stream`): what a download hands on at a time.
STREAM_PIECE_BYTES = 1024 * 1024
STREAM_DEPTH = 4  # pieces a stream read on the event loop holds at most (LoopReadingStore)


class StreamingStore(ObjectStore, Protocol):
    """A store that reads a range as one stream (S3: one GET), not in ranged reads of its own."""

    def stream(self, key: str, start: int = 0, length: int | None = None) -> Iterator[bytes]:
        """The bytes of `key` from `start` (`length` of them, to the end when None), in pieces of
        at most STREAM_PIECE_BYTES, read as the caller takes them."""
        ...


def supports_streaming(store: ObjectStore) -> TypeGuard[StreamingStore]:
    return hasattr(store, "stream")


# The longest a presigned read may last: a URL that leaks is good for this long at most.
PRESIGNED_TTL_MAX_S = 15 * 60


class PresigningStore(ObjectStore, Protocol):
    """A store that can hand out a URL to read one object without credentials (S3's presigned GET),
    so that a client reads it from the bucket, not through the depot."""

    def presigned_get(self, key: str, expires_s: int) -> str:
        """A URL good for GET (with any Range) of `key` alone, for `expires_s` seconds (at most
        PRESIGNED_TTL_MAX_S). It carries a signature, never a secret key."""
        ...


def supports_presigned(store: ObjectStore) -> TypeGuard[PresigningStore]:
    return hasattr(store, "presigned_get")


class LoopReadingStore(ObjectStore, Protocol):
    """A store whose reads can run on the event loop itself (S3: one GET signed for the read, its
    socket read by the loop as it writes the client's; services/storage/loop_get.py says why)."""

    loop_reads: bool  # False where they cannot (S3 behind a proxy): the caller reads in a thread

    def loop_read(self, key: str, start: int, length: int) -> AsyncIterator[memoryview]:
        """`key` from `start` to its end (`length` bytes, as the caller knows the object), in pieces
        of at most STREAM_PIECE_BYTES, read as the caller takes them, STREAM_DEPTH ahead at most."""
        ...

    def loop_splices(self) -> bool:
        """Whether `loop_open` can hand a read over (the store spoken to in plain HTTP)."""
        ...

    def loop_open(self, key: str, start: int, length: int) -> AbstractAsyncContextManager[Source]:
        """As `loop_read`, the answer's head read, its body left in the socket for the caller to
        splice to a client while the context is open (only where `loop_splices`)."""
        ...


def supports_loop_reads(store: ObjectStore) -> TypeGuard[LoopReadingStore]:
    return getattr(store, "loop_reads", False) is True


class RangeReader:
    """An object read as a file, in ranged pieces: lets a copy between stores run in constant memory."""

    def __init__(self, store: ObjectStore, key: str, size: int, piece: int = 8 * 1024 * 1024) -> None:
        self._store, self._key, self._size, self._piece = store, key, size, piece
        self._position = 0
        self._buffer = b""

    def read(self, n: int = -1) -> bytes:
        want = self._size - self._position if n is None or n < 0 else n
        while len(self._buffer) < want and self._position < self._size:
            length = min(max(self._piece, want - len(self._buffer)), self._size - self._position)
            self._buffer += self._store.get_range(self._key, self._position, length)
            self._position += length
        out, self._buffer = self._buffer[:want], self._buffer[want:]
        return out


def copy_object(source: ObjectStore, target: ObjectStore, key: str) -> ObjectInfo:
    """Copy `key` from one store to another (streamed); the copy's size is checked."""
    size = source.head(key).size
    info = target.put(key, RangeReader(source, key, size))  # type: ignore[arg-type]
    if info.size != size:
        raise StorageError(f"copy of {key!r} to {target.url} has {info.size} bytes, expected {size}")
    return info


def check_key(key: str) -> str:
    if not key or key.startswith("/") or not _SAFE_KEY.match(key) or ".." in key.split("/"):
        raise ValueError(f"object key {key!r} must be a relative path of A-Z a-z 0-9 . _ - / =")
    return key


def open_store(
    url: str,
    *,
    endpoint_url: str | None = None,
    region: str | None = None,
    uploads: Uploads | None = None,
    presign_endpoint_url: str | None = None,
    loop_reads: bool = True,
) -> ObjectStore:
    """The store behind `url`: `file:///path` or `s3://bucket/prefix` (boto3 is imported only for S3).
    `presign_endpoint_url`: the endpoint an S3 store's presigned URLs name (default: `endpoint_url`),
    for clients that reach the bucket by another address than the depot does. `loop_reads`: whether an
    S3 store may read on the event loop (LoopReadingStore; False: botocore alone sends its requests)."""
    parsed = urlparse(url)
    if parsed.scheme == "file":
        from services.storage.local import LocalStore

        return LocalStore(url)
    if parsed.scheme == "s3":
        from services.storage.s3 import S3Store

        return S3Store(
            url,
            endpoint_url=endpoint_url,
            region=region,
            uploads=uploads,
            presign_endpoint_url=presign_endpoint_url,
            loop_reads=loop_reads,
        )
    raise StorageError(f"unsupported store URL {url!r}: use file:///PATH or s3://BUCKET/PREFIX")


class ObjectFile(io.RawIOBase):
    """An object of a store read as a seekable file, by ranged reads: what reading a footer from
    the end of a recording takes, without fetching the recording."""

    def __init__(self, store: ObjectStore, key: str, size: int) -> None:
        self._store, self._key, self._size = store, key, size
        self._position = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._position, os.SEEK_END: self._size}[whence]
        self._position = max(0, base + offset)
        return self._position

    def tell(self) -> int:
        return self._position

    def read(self, size: int = -1) -> bytes:
        end = self._size if size is None or size < 0 else min(self._size, self._position + size)
        if end <= self._position:
            return b""
        data = self._store.get_range(self._key, self._position, end - self._position)
        self._position += len(data)
        return data
