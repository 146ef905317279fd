"""An object store that records its ranged reads, for tests of how much a reader reads."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import BinaryIO, NamedTuple

from services.storage.objectstore import ObjectInfo, ObjectStore


class RangedRead(NamedTuple):
    key: str
    start: int
    length: int | None  # as asked (None: to the end)
    got: int  # bytes returned


@dataclass
class CountingStore:
    """`inner`, with every `get_range` recorded in `reads`."""

    inner: ObjectStore
    reads: list[RangedRead] = field(default_factory=list)
    url: str = ""

    def __post_init__(self) -> None:
        self.url = self.inner.url

    @property
    def read(self) -> int:
        """The bytes all ranged reads returned."""
        return sum(r.got for r in self.reads)

    def put(self, key: str, data: bytes | BinaryIO) -> ObjectInfo:
        return self.inner.put(key, data)

    def get_range(self, key: str, start: int = 0, length: int | None = None) -> bytes:
        data = self.inner.get_range(key, start, length)
        self.reads.append(RangedRead(key, start, length, len(data)))
        return data

    def head(self, key: str) -> ObjectInfo:
        return self.inner.head(key)

    def list(self, prefix: str = "") -> Iterator[ObjectInfo]:
        return self.inner.list(prefix)

    def delete(self, key: str) -> None:
        self.inner.delete(key)
