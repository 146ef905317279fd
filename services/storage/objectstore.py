"""The object-store interface and `open_store(url)`, which picks the backend by URL scheme:
`file:///path` (a local folder) or `s3://bucket/prefix` (S3 and S3-compatible servers)."""

from __future__ import annotations

import datetime as dt
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import BinaryIO, Protocol
from urllib.parse import urlparse

from services.errors import ErrorCode, FleetError

_SAFE_KEY = re.compile(r"^[A-Za-z0-9._\-/]+$")


class ObjectNotFoundError(FleetError):
    code = ErrorCode.NOT_FOUND


class StorageError(FleetError):
    code = ErrorCode.UNAVAILABLE


@dataclass(frozen=True)
class ObjectInfo:
    key: str
    size: int
    last_modified: dt.datetime
    storage_class: str | None = None


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


def check_key(key: str) -> str:
    if not key or key.startswith("/") or not _SAFE_KEY.match(key) or ".." in key.split("/"):
        raise ValueError(f"object key {key!r} must be a relative path of A-Z a-z 0-9 . _ - /")
    return key


def open_store(url: str, *, endpoint_url: str | None = None, region: str | None = None) -> ObjectStore:
    """The store behind `url`: `file:///path` or `s3://bucket/prefix` (boto3 is imported only for S3)."""
    parsed = urlparse(url)
    if parsed.scheme == "file":
        from services.storage.local import LocalStore

        return LocalStore(url)
    if parsed.scheme == "s3":
        from services.storage.s3 import S3Store

        return S3Store(url, endpoint_url=endpoint_url, region=region)
    raise StorageError(f"unsupported store URL {url!r}: use file:///PATH or s3://BUCKET/PREFIX")
