"""Where a query reads a dataset's runs: a sealed run's index and footer read once and then kept
(its schema from the footer alone, by ranged reads), a hot run from its file, a cold run named as
unreadable."""

from __future__ import annotations

import io
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import BinaryIO

import pytest

from catalog import queries
from catalog.db import session_scope
from services.redap import sources
from services.redap.datasets import dataset_by_entry
from services.redap.depot import Depot
from services.redap.tuid import Tuid
from services.storage.objectstore import ObjectInfo, ObjectStore
from tests.services.redap.serving import DepotNode, build_node
from tests.services.rrd.recordings import generate_scenes

pytestmark = pytest.mark.sdk


@dataclass
class CountingStore:
    """A store that counts its ranged reads."""

    inner: ObjectStore
    reads: list[tuple[str, int, int | None]] = field(default_factory=list)
    url: str = ""

    def __post_init__(self) -> None:
        self.url = self.inner.url

    def put(self, key: str, data: bytes | BinaryIO) -> ObjectInfo:
        return self.inner.put(key, data)

    def get_range(self, key: str, start: int = 0, length: int | None = None) -> bytes:
        self.reads.append((key, start, length))
        return self.inner.get_range(key, start, length)

    def head(self, key: str) -> ObjectInfo:
        return self.inner.head(key)

    def list(self, prefix: str = "") -> Iterator[ObjectInfo]:
        return self.inner.list(prefix)

    def delete(self, key: str) -> None:
        self.inner.delete(key)


@pytest.fixture(scope="module")
def points(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return generate_scenes(("points",), tmp_path_factory.mktemp("sources"))["points"].path


@pytest.fixture
def node(tmp_path: Path) -> Iterator[DepotNode]:
    sources.clear_caches()
    made = build_node(tmp_path / "node")
    yield made
    made.close()
    sources.clear_caches()


def _sources(depot: Depot) -> list[sources.IndexedRecordingSource]:
    with session_scope(depot.catalog) as session:
        entry = Tuid.parse(queries.datasets(session)[0].entry_id)
        return sources.dataset_sources(depot, session, dataset_by_entry(session, entry), depot.clock())


def test_a_sealed_run_is_read_once_then_kept(node: DepotNode, points: Path):
    node.upload(points)
    node.seal_all()
    counting = CountingStore(node.tiers.warm)
    depot = replace(node.depot, node=replace(node.depot.node, tiers=replace(node.tiers, warm=counting)))
    (source,) = _sources(depot)
    assert source.prefix is not None and source.hot is None and len(source.digest) == 64

    schema = sources.run_schema(depot, source)
    footer_reads = list(counting.reads)
    assert footer_reads and all(key.endswith("/recording.rrd") for key, _, _ in footer_reads)
    assert sum(length or 0 for _, _, length in footer_reads) < source.size  # the footer, not the recording
    assert "/world/points:Points3D:positions" in schema.names

    found = sources.run_chunks(depot, source)
    assert len(found.rows) == 7 and all(r.chunk_id in found.uncompressed for r in found.rows)
    assert any(key.endswith("/chunks.parquet") for key, _, _ in counting.reads)
    before = len(counting.reads)
    assert sources.run_chunks(depot, source) is found and sources.run_schema(depot, source).equals(schema)
    assert len(counting.reads) == before  # kept: nothing read again
    sources.run_chunks(depot, replace(source, digest="another recording"))
    assert len(counting.reads) > before  # a run sealed again is another recording


def test_a_hot_run_is_read_from_its_file(node: DepotNode, points: Path):
    node.upload(points)
    (source,) = _sources(node.depot)
    assert source.hot is not None and source.prefix is None
    found = sources.run_chunks(node.depot, source)
    data = source.hot.path.read_bytes()
    for row in found.rows:  # each row's frame: an ArrowMsg header, then the message
        assert int.from_bytes(data[row.offset : row.offset + 8], "little") == 2
        assert int.from_bytes(data[row.offset + 8 : row.offset + 16], "little") == row.length - 16
    assert {r.entity_path for r in found.rows} == {"/__properties", "/world/points", "/world/sparse"}


def test_an_object_reads_as_a_seekable_file(node: DepotNode):
    node.tiers.warm.put("x/object", io.BytesIO(b"0123456789"))
    handle = sources.ObjectFile(node.tiers.warm, "x/object", 10)
    assert handle.seek(0, io.SEEK_END) == 10
    assert handle.seek(-4, io.SEEK_END) == 6 and handle.read(2) == b"67" and handle.tell() == 8
    assert handle.read() == b"89" and handle.read(5) == b""
    handle.seek(1)
    assert handle.read(3) == b"123"
