"""Where a query reads a dataset's runs: a sealed run's index and footer read once and then kept
(its schema from the footer alone, by ranged reads), a hot run from its file, a cold run named as
unreadable."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from catalog import queries
from catalog.db import session_scope
from services.redap import sources
from services.redap.datasets import dataset_by_entry
from services.redap.depot import Depot
from services.redap.tuid import Tuid
from tests.services.redap.serving import DepotNode, build_node
from tests.services.rrd.recordings import Recording
from tests.services.storage.counting import CountingStore

pytestmark = pytest.mark.sdk


@pytest.fixture(scope="module")
def points(recordings: dict[str, Recording]) -> Path:
    return recordings["points"].path


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
    assert footer_reads and all(r.key.endswith("/recording.rrd") for r in footer_reads)
    assert sum(r.length or 0 for r in footer_reads) < source.size  # the footer, not the recording
    assert "/world/points:Points3D:positions" in schema.names

    found = sources.run_chunks(depot, source)
    assert len(found.rows) == 7 and all(r.chunk_id in found.uncompressed for r in found.rows)
    assert any(r.key.endswith("/chunks.parquet") for r in counting.reads)
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
