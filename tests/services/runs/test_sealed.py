"""Serving sealed runs: ranged reads planned from `chunks.parquet`, and one URL whatever the tier.

Runs are logged with the real SDK, uploaded into a node over local or S3 (moto) stores, served
hot, promoted, and served again; what comes out is checked with `rerun rrd verify` and compared
chunk by chunk with what the hot download gave for the same request.
"""

from __future__ import annotations

import dataclasses
import io
import json
import subprocess
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient

from catalog import queries
from catalog.db import session_scope
from services.api import http_protocol
from services.api.app import create_app
from services.retention import archive
from services.retention.service import PROMOTE, plan, run_plan
from services.rrd import ArrowMessage, StoreKind, iter_events
from services.rrd.chunk import chunk_meta, read_chunk
from services.rrd.chunk_index import CHUNK, IndexRow
from services.rrd.frames import STREAM_HEADER_SIZE
from services.rrd.manifest import is_property_entity
from services.runs import indexed
from services.runs.download import EntityFilter, TimeWindow
from services.runs.latest_at import ChunkEntry
from services.runs.sealed import indexed_recording, stream_sealed
from services.sealed import read
from services.sealed.read import open_sealed
from services.sealed.tiers import Tiers
from services.sealed.write import INDEX, RECORDING
from services.storage.objectstore import open_store
from services.storage.s3 import S3Store
from services.storage.splice import splice_exactly
from tests.conftest import find_rerun
from tests.services.api.served import served
from tests.services.retention import conftest as retention
from tests.services.retention.conftest import Clock, Node, NodeFactory, log_run
from tests.services.runs.decoded import stream_run
from tests.services.storage import s3_backends
from tests.services.storage.counting import CountingStore

pytestmark = pytest.mark.sdk
tiers, make_node = retention.tiers, retention.make_node  # the retention tests' fixtures: stores and nodes
seaweed_endpoint = s3_backends.seaweed_endpoint  # a real S3 server on loopback

PROMOTE_AFTER_S = 600.0
WIDE = "0123456789abcdef0123456789abcdef"  # ten entities
CHUNKY = "fedcba9876543210fedcba9876543210"  # ten entities, five rows a chunk
SPARSE = "5a5a5a5a5a5a5a5a5a5a5a5a5a5a5a5a"  # one entity, one component only in some rows, compacted


@pytest.fixture(autouse=True)
def no_index_parsed_yet() -> Iterator[None]:
    """Each test starts as a depot that has parsed no chunk index: the tests of one process seal the
    same recordings, often within the same second, and such a recording has the same store, prefix,
    size and version as another test's (its parsed index, perhaps an older one a test wrote, would
    be found in the cache, and the reads a test counts would not happen)."""
    with read._indexes_lock:
        read._indexes.clear()
    yield


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Logged once for the module: a ten-entity run (one chunk an entity) and one with several chunks an entity."""
    root = tmp_path_factory.mktemp("sealed-runs")
    wide = log_run(root / "wide.rrd", WIDE, entities=10)
    with pytest.MonkeyPatch.context() as env:
        # the SDK's batcher cuts chunks by RERUN_FLUSH_NUM_ROWS (RERUN_CHUNK_MAX_ROWS, which log_run's
        # chunk_rows sets, is the viewer store's compaction limit and leaves logged chunks whole)
        env.setenv("RERUN_FLUSH_NUM_ROWS", "5")
        chunky = log_run(root / "chunky.rrd", CHUNKY, entities=10, chunk_rows=5)
        sparse = _log_sparse(root / "sparse-logged.rrd")
    compacted = root / "sparse.rrd"
    subprocess.run(
        [find_rerun() or "rerun", "rrd", "optimize", "--max-rows", "10", str(sparse), "-o", str(compacted)],
        check=True,
        capture_output=True,
        timeout=120,
    )
    return {"wide": wide, "chunky": chunky, "sparse": compacted}


def _log_sparse(path: Path) -> Path:
    """/world/sparse: positions every frame, colors at frames 0-2 and 7 only (a partial update)."""
    script = f"""
import numpy as np, rerun as rr
rr.init("fleet-test", recording_id={SPARSE!r}, spawn=False)
rr.save({str(path)!r})
for i in range(30):
    rr.set_time("frame", sequence=i)
    positions = np.full((3, 3), i, dtype=np.float32)
    if i < 3 or i == 7:
        rr.log("/world/sparse", rr.Points3D(positions, colors=[255, 0, 0] if i < 3 else [0, 255, 0]))
    else:
        rr.log("/world/sparse", rr.Points3D(positions))
"""
    subprocess.run([sys.executable, "-c", script], check=True, timeout=120)
    return path


def _node(make_node: NodeFactory, tiers: Tiers, run: Path) -> tuple[Node, str]:
    node = make_node(tiers, clock=Clock(), promote_after_s=PROMOTE_AFTER_S)
    report = node.upload(run)
    run_ids = list(node.ingest.runs)
    assert len(run_ids) == 1, report
    return node, run_ids[0]


def _promote(node: Node, run_id: str) -> str:
    """Promote the node's hot run the way the scheduler does; returns its warm prefix."""
    node.clock.advance(seconds=PROMOTE_AFTER_S + 1)
    actions = plan(node.retention, [PROMOTE])
    assert [a.run_id for a in actions] == [run_id]
    outcomes = run_plan(node.retention, actions)
    assert all(o.ok for o in outcomes), [o.detail for o in outcomes]
    assert run_id not in node.ingest.runs
    with session_scope(node.catalog) as session:
        run, life = queries.get_run(session, run_id), queries.lifecycle(session, run_id)
        assert run is not None and run.tier == "warm" and life is not None
        return life.prefix


def _hot(node: Node, run_id: str, entities: EntityFilter) -> bytes:
    hot = node.ingest.runs[run_id].hot
    return b"".join(stream_run(hot.path, hot.size, entities))


def _chunks(data: bytes) -> list[tuple[str, bytes, int]]:
    """(entity, chunk id, rows) of every recording chunk of an .rrd stream."""
    out = []
    for event in iter_events(io.BytesIO(data)):
        if isinstance(event, ArrowMessage) and event.store_id.kind == StoreKind.RECORDING:
            meta = chunk_meta(event)
            out.append((meta.entity_path, meta.chunk_id, meta.num_rows))
    return out


def _ids(data: bytes) -> set[bytes]:
    """Every chunk id of a stream (recording and blueprint)."""
    return {chunk_meta(e).chunk_id for e in iter_events(io.BytesIO(data)) if isinstance(e, ArrowMessage)}


def _rows(data: bytes) -> Counter[str]:
    rows: Counter[str] = Counter()
    for entity, _, n in _chunks(data):
        rows[entity] += n
    return rows


def _cells(data: bytes, timeline: str = "frame") -> set[tuple[str, str, int]]:
    """(entity, component, time) of every non-null value on `timeline` in the recording's chunks."""
    out = set()
    for event in iter_events(io.BytesIO(data)):
        if not isinstance(event, ArrowMessage) or event.store_id.kind != StoreKind.RECORDING:
            continue
        meta, batch = chunk_meta(event), read_chunk(event)
        index = next((ix for ix in meta.layout.indexes if ix.name == timeline), None)
        if index is None:
            continue
        times = batch.column(index.position).cast("int64").to_pylist()
        for col in meta.layout.data:
            for t, valid in zip(times, batch.column(col.position).is_valid().to_pylist(), strict=True):
                if valid:
                    out.add((meta.entity_path, col.component, t))
    return out


def _verify(rerun_bin: str, data: bytes, path: Path) -> None:
    path.write_bytes(data)
    verify = subprocess.run([rerun_bin, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stdout + verify.stderr


# --- ranged reads ------------------------------------------------------------------------------


def test_one_entity_of_ten_reads_a_small_part_of_the_object(
    tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path], rerun_bin: str, tmp_path: Path
):
    node, run_id = _node(make_node, tiers, runs["wide"])
    one = EntityFilter(include=["/world/e3"])
    hot = _hot(node, run_id, one)
    prefix = _promote(node, run_id)
    counting = CountingStore(tiers.warm)
    size = tiers.warm.head(f"{prefix}/{RECORDING}").size
    warm = b"".join(stream_sealed(open_sealed(counting, prefix), one))
    _verify(rerun_bin, warm, tmp_path / "warm.rrd")
    assert {e for e, _, _ in _chunks(warm)} >= {"/world/e3"}
    assert not {e for e, _, _ in _chunks(warm)} & {f"/world/e{i}" for i in range(10) if i != 3}
    assert _ids(warm) == _ids(hot) and _rows(warm) == _rows(hot)
    assert counting.read < 0.15 * size, (counting.read, size, counting.reads)
    assert any(key.endswith("chunks.parquet") for key, *_ in counting.reads)  # the plan's read is counted
    # the entity's own chunk is in there: the reads cover at least what they serve
    e3 = sum(
        len(e.payload)
        for e in iter_events(io.BytesIO(warm))
        if isinstance(e, ArrowMessage) and chunk_meta(e).entity_path == "/world/e3"
    )
    assert 0.05 * size < e3 <= counting.read


def test_a_filtered_download_reads_the_stream_header_with_its_first_messages(
    tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path]
):
    """The stream's 12 bytes come with the run's first messages (its store info follows them): one
    read, not a store's first byte twice before anything is sent."""
    node, run_id = _node(make_node, tiers, runs["wide"])
    one = EntityFilter(include=["/world/e3"])
    hot = _hot(node, run_id, one)
    prefix = _promote(node, run_id)
    counting = CountingStore(tiers.warm)
    warm = b"".join(stream_sealed(open_sealed(counting, prefix), one))
    assert _ids(warm) == _ids(hot) and _rows(warm) == _rows(hot)
    recording_reads = [(start, got) for key, start, _, got in counting.reads if key.endswith(RECORDING)]
    from_start = [got for start, got in recording_reads if start == 0]  # (reads are recorded as they end)
    assert len(from_start) == 1 and from_start[0] > STREAM_HEADER_SIZE, recording_reads


@pytest.mark.parametrize("old_index", [False, True])
def test_exact_window_reads_only_the_candidate_chunks(
    tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path], rerun_bin: str, tmp_path: Path, old_index: bool
):
    """Finding the newest rows before the window reads the few chunks that may hold them (ranged
    reads), not the run: with per-component ranges in the index, and without (an older index, read
    newest chunk first until nothing older can matter)."""
    node, run_id = _node(make_node, tiers, runs["chunky"])
    one = EntityFilter(include=["/world/e3"])
    window = TimeWindow("frame", 15, 16, latest_at=True, exact=True)
    hot = node.ingest.runs[run_id].hot
    expected = b"".join(stream_run(hot.path, hot.size, one, window=window))
    prefix = _promote(node, run_id)
    if old_index:
        index = pq.read_table(io.BytesIO(tiers.warm.get_range(f"{prefix}/{INDEX}")))
        out = io.BytesIO()
        pq.write_table(index.drop_columns(["component_ranges"]), out)
        tiers.warm.put(f"{prefix}/{INDEX}", out.getvalue())
    counting = CountingStore(tiers.warm)
    sealed = open_sealed(counting, prefix)
    assert (sealed.rows[-1].component_ranges is None) == old_index
    warm = b"".join(stream_sealed(sealed, one, window=window))
    _verify(rerun_bin, warm, tmp_path / "warm.rrd")
    assert _cells(warm) == _cells(expected) and ("/world/e3", "Points3D:positions", 14) in _cells(warm)
    size = tiers.warm.head(f"{prefix}/{RECORDING}").size
    e3_chunk = max(r.length for r in sealed.rows if r.entity_path == "/world/e3")
    recording_reads = sum(n for key, _, _, n in counting.reads if key.endswith(RECORDING))
    # the chunk before the window (read to pick its row, then served) and the one the window starts
    # (served), with the older index also the chunk before it (read to learn its ranges)
    assert recording_reads <= (5 if old_index else 4) * e3_chunk + 64 * 1024, (recording_reads, e3_chunk)
    assert recording_reads < 0.1 * size, (recording_reads, size)


def test_windows_asked_one_after_another_are_planned_from_the_cached_index(
    tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path], monkeypatch: pytest.MonkeyPatch
):
    """A sealed run's parsed index is kept with what planning worked out from it: a window looks at
    the chunks of the entities it asks for that it may keep, each once, and the next one looks at none
    of them again (a run of many GB has tens of thousands of rows), and plans what a fresh index plans."""
    node, run_id = _node(make_node, tiers, runs["chunky"])
    prefix = _promote(node, run_id)
    looked_at: list[bytes] = []
    entry = indexed._entry

    def counted(row: IndexRow, timeline: str) -> ChunkEntry:
        looked_at.append(row.chunk_id or b"")
        return entry(row, timeline)

    monkeypatch.setattr(indexed, "_entry", counted)
    e3, e4 = EntityFilter(include=["/world/e3"]), EntityFilter(include=["/world/e4"])
    first = b"".join(stream_sealed(open_sealed(tiers.warm, prefix), e3, window=TimeWindow("frame", 15, 16)))
    sealed = open_sealed(tiers.warm, prefix)
    e3_chunks = {r.chunk_id for r in sealed.rows if r.entity_path == "/world/e3"}
    properties = {r.chunk_id for r in sealed.rows if is_property_entity(r.entity_path or "")}
    seen = set(looked_at)
    assert (
        seen <= e3_chunks | properties
        and len(looked_at) == len(seen)
        and _ids(first) - {b""} <= seen | {r.chunk_id for r in sealed.rows if r.store_kind == "blueprint"}
    )
    looked_at.clear()
    again = b"".join(stream_sealed(open_sealed(tiers.warm, prefix), e3, window=TimeWindow("frame", 15, 16)))
    assert looked_at == [] and again == first
    later = b"".join(stream_sealed(open_sealed(tiers.warm, prefix), e3, window=TimeWindow("frame", 20, 24)))
    assert not seen & set(looked_at) and set(looked_at) <= e3_chunks | properties
    looked_at.clear()
    b"".join(stream_sealed(open_sealed(tiers.warm, prefix), e4, window=TimeWindow("frame", 15, 16)))
    assert {r.entity_path for r in sealed.rows if r.chunk_id in set(looked_at)} == {"/world/e4"}
    read._indexes.clear()  # planned from a fresh parse
    fresh = b"".join(stream_sealed(open_sealed(tiers.warm, prefix), e3, window=TimeWindow("frame", 20, 24)))
    assert _ids(fresh) == _ids(later) and _rows(fresh) == _rows(later)


def test_a_window_makes_only_the_index_rows_of_the_entities_it_asks_for(
    tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path]
):
    """A sealed run's index is read as columns: a window of one entity makes the rows of the other
    messages and of those of that entity's chunks (with the properties' and the blueprint's) it may
    keep, not every row, and serves what the rows made all at once serve."""
    node, run_id = _node(make_node, tiers, runs["chunky"])
    prefix = _promote(node, run_id)
    e3, window = EntityFilter(include=["/world/e3"]), TimeWindow("frame", 15, 16)
    read._indexes.clear()
    lazily = b"".join(stream_sealed(open_sealed(tiers.warm, prefix), e3, window=window))
    index = open_sealed(tiers.warm, prefix).index  # the one the window read, cached
    made = index.rows_made
    rows = index.all()
    wanted = [r for r in rows if r.kind != CHUNK or r.store_kind == "blueprint" or e3(r.entity_path or "")]
    others = [r for r in rows if r.kind != CHUNK]
    assert len(others) + len(set(_ids(lazily))) <= made < len(wanted) < len(rows) / 2  # (not the entity's others)
    as_list = dataclasses.replace(indexed_recording(open_sealed(tiers.warm, prefix)), index=lambda: list(rows))
    assert b"".join(indexed.stream_indexed(as_list, e3, window=window)) == lazily  # planned from every row


def test_unfiltered_warm_download_is_the_sealed_object(tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path]):
    node, run_id = _node(make_node, tiers, runs["wide"])
    prefix = _promote(node, run_id)
    stored = tiers.warm.get_range(f"{prefix}/{RECORDING}")
    counting = CountingStore(tiers.warm)
    served = b"".join(stream_sealed(open_sealed(counting, prefix), EntityFilter()))
    assert served == stored and len(stored) > 1_000_000
    assert not any(key.endswith(INDEX) for key, *_ in counting.reads)  # the chunk index is not needed
    client = TestClient(_app(node))
    response = client.get(f"/v1/runs/{run_id}/recording.rrd")
    assert response.status_code == 200 and response.content == stored


def _sealed_on_seaweed(
    endpoint: str, make_node: NodeFactory, run: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> tuple[Node, str, bytes]:
    """A node whose tiers are in the SeaweedFS at `endpoint`, with `run` uploaded and promoted: the
    node, the run's id and its sealed recording's bytes."""
    for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
        monkeypatch.setenv(name, "test")
    warm, cold = (
        open_store(f"s3://{s3_backends.BUCKET}/{tmp_path.name}/{tier}", endpoint_url=endpoint, region="us-east-1")
        for tier in ("warm", "cold")
    )
    node, run_id = _node(make_node, Tiers(warm, cold), run)
    return node, run_id, warm.get_range(f"{_promote(node, run_id)}/{RECORDING}")


@pytest.mark.s3server
@pytest.mark.slow
def test_a_whole_download_from_s3_is_read_on_the_event_loop(
    seaweed_endpoint: str,
    make_node: NodeFactory,
    runs: dict[str, Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
):
    """On a real S3 server the sealed object goes to the client by one GET the event loop reads
    (`S3Store.loop_read`), not through botocore in a thread."""
    node, run_id, stored = _sealed_on_seaweed(seaweed_endpoint, make_node, runs["wide"], tmp_path, monkeypatch)

    def in_a_thread(*_: object, **__: object) -> None:
        raise AssertionError("the whole object was read through botocore in a thread")

    monkeypatch.setattr(S3Store, "stream", in_a_thread)
    response = TestClient(_app(node)).get(f"/v1/runs/{run_id}/recording.rrd")
    assert response.status_code == 200 and response.content == stored
    assert response.headers["content-length"] == str(len(stored))


@pytest.mark.s3server
@pytest.mark.slow
def test_a_whole_download_from_s3_is_spliced_into_the_client_s_connection(
    seaweed_endpoint: str,
    make_node: NodeFactory,
    runs: dict[str, Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
):
    """Behind the REST port's real HTTP server, the sealed object's bytes go from the store's socket
    to the client's by splice (all but those that came with the GET's head), the connection stays
    good for the next request, and a filtered download is streamed as before."""
    node, run_id, stored = _sealed_on_seaweed(seaweed_endpoint, make_node, runs["wide"], tmp_path, monkeypatch)
    spliced: list[int] = []

    async def counted(src: int, dst: int, count: int, stall_s: float) -> None:
        await splice_exactly(src, dst, count, stall_s)
        spliced.append(count)

    monkeypatch.setattr(http_protocol, "splice_exactly", counted)
    with served(_app(node)) as url, httpx.Client(base_url=url) as client:
        whole = client.get(f"/v1/runs/{run_id}/recording.rrd")
        assert whole.status_code == 200 and whole.content == stored
        assert len(spliced) == 1 and len(stored) - 65536 < spliced[0] <= len(stored)
        one = client.get(f"/v1/runs/{run_id}/recording.rrd", params={"include": "/world/e3"})
        assert one.status_code == 200 and one.content == _get(TestClient(_app(node)), run_id, {"include": "/world/e3"})
        assert len(spliced) == 1  # a filtered download is made by the depot, not spliced
        again = client.get(f"/v1/runs/{run_id}/recording.rrd")
        assert again.content == stored and len(spliced) == 2
        assert client.get("/healthz").status_code == 200  # the kept-alive connection after them


# --- one URL, any tier -------------------------------------------------------------------------

QUERIES: list[dict[str, Any]] = [
    {},
    {"include": "/world/e3"},
    {"include": ["/world/e1", "/world/e7"]},
    {"exclude": "/world/e3"},
    {"include": "/world/**", "exclude": ["/world/e0", "/world/e9"]},
    {"blueprint": "false"},
    {"timeline": "frame", "start": "12", "end": "17"},
    {"timeline": "frame", "start": "12", "end": "17", "latest_at": "false"},
    {"timeline": "frame", "start": "15", "end": "17"},
    {"timeline": "frame", "start": "15", "end": "17", "latest_at": "false"},
    {"timeline": "frame", "start": "20"},
    {"timeline": "frame", "end": "3"},
    {"timeline": "sim", "start": "1.2s", "end": "1700ms"},
    {"timeline": "frame", "start": "12", "end": "17", "include": "/world/e3"},
    {"timeline": "frame", "start": "12", "end": "17", "exact": "true"},
    {"timeline": "frame", "start": "12", "end": "17", "latest_at": "false", "exact": "true"},
    {"timeline": "sim", "start": "0.9s", "end": "2.05s", "exact": "true", "exclude": "/logs"},
]


def _app(node: Node) -> Any:
    return create_app(node.context, node.ingest, node.retention)


def _get(client: TestClient, run_id: str, params: dict[str, Any]) -> bytes:
    response = client.get(f"/v1/runs/{run_id}/recording.rrd", params=params)
    assert response.status_code == 200, (params, response.text)
    return bytes(response.content)


def test_same_url_serves_the_same_chunks_hot_and_warm(
    tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path], rerun_bin: str, tmp_path: Path
):
    node, run_id = _node(make_node, tiers, runs["chunky"])
    client = TestClient(_app(node))
    per_entity = Counter(e for e, _, _ in _chunks(_get(client, run_id, {})))
    assert per_entity["/world/e3"] >= 3, per_entity  # several chunks an entity, so windows choose among them
    hot = {i: _get(client, run_id, q) for i, q in enumerate(QUERIES)}
    _promote(node, run_id)
    for i, params in enumerate(QUERIES):
        warm = _get(client, run_id, params)
        _verify(rerun_bin, warm, tmp_path / f"warm-{i}.rrd")
        if params.get("exact") == "true":  # trimmed chunks are re-encoded: new ids, the same rows
            assert Counter((e, n) for e, _, n in _chunks(warm)) == Counter((e, n) for e, _, n in _chunks(hot[i]))
        else:
            assert _ids(warm) == _ids(hot[i]), (params, len(_ids(warm)), len(_ids(hot[i])))
        assert _rows(warm) == _rows(hot[i]), params
        assert _cells(warm, params.get("timeline", "frame")) == _cells(hot[i], params.get("timeline", "frame"))

    # the windows pick some chunks and leave others: the comparisons above are not all or nothing
    def ids_of(params: dict[str, Any]) -> set[bytes]:
        return _ids(hot[QUERIES.index(params)])

    # a window starting on a chunk boundary (15) needs the chunks before it for its latest-at rows; one
    # starting inside chunks (12) does not: the chunks straddling the start hold the newest earlier rows
    with_latest = ids_of({"timeline": "frame", "start": "15", "end": "17"})
    window = ids_of({"timeline": "frame", "start": "15", "end": "17", "latest_at": "false"})
    assert 0 < len(window) < len(with_latest) < len(_ids(hot[0]))
    assert ids_of({"timeline": "frame", "start": "12", "end": "17"}) == ids_of(
        {"timeline": "frame", "start": "12", "end": "17", "latest_at": "false"}
    )
    exact = _rows(hot[QUERIES.index({"timeline": "frame", "start": "12", "end": "17", "exact": "true"})])
    assert exact["/world/e3"] == 6 + 1, exact  # frames 12-17, and one row before them


def test_cold_deleted_and_unknown_runs(tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path]):
    node, run_id = _node(make_node, tiers, runs["wide"])
    prefix = _promote(node, run_id)
    stored = tiers.warm.get_range(f"{prefix}/{RECORDING}")
    client = TestClient(_app(node))
    assert archive.archive(run_id, tiers, node.catalog, node.clock(), "default").startswith("archived")
    for params in ({}, {"include": "/world/e3"}):
        cold = client.get(f"/v1/runs/{run_id}/recording.rrd", params=params)
        assert cold.status_code == 409, cold.text
        message = cold.json()["message"]
        assert f"POST /v1/runs/{run_id}/restore" in message and f"fleet runs restore {run_id}" in message
    archive.request_restore(run_id, tiers, node.catalog, node.clock(), "test", 7)
    restoring = client.get(f"/v1/runs/{run_id}/recording.rrd")
    assert restoring.status_code == 409 and "under way" in restoring.json()["message"]
    assert archive.advance_restore(run_id, tiers, node.catalog, node.clock()) == "restored"
    restored = client.get(f"/v1/runs/{run_id}/recording.rrd")
    assert restored.status_code == 200 and restored.content == stored
    assert archive.delete(run_id, tiers, node.catalog, node.clock(), "alice", None).startswith("deleted")
    gone = client.get(f"/v1/runs/{run_id}/recording.rrd")
    assert gone.status_code == 410 and "alice" in gone.json()["message"], gone.text
    unknown = client.get("/v1/runs/no-such-run/recording.rrd")
    assert unknown.status_code == 404 and "no-such-run" in unknown.json()["message"]


def test_warm_download_headers(tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path]):
    node, run_id = _node(make_node, tiers, runs["wide"])
    _promote(node, run_id)
    client = TestClient(_app(node))
    url = f"/v1/runs/{run_id}/recording.rrd"
    whole, again = client.get(url), client.get(url)
    one = client.get(url, params={"include": "/world/e3"})
    for response in (whole, again, one):
        assert response.status_code == 200
        assert response.headers["content-disposition"] == f'attachment; filename="{run_id}.rrd"'
        assert response.headers["content-type"] == "application/octet-stream"
        assert run_id in response.headers["etag"]
    assert whole.headers["etag"] == again.headers["etag"] != one.headers["etag"]
    # The whole object's size is known before it is sent (a client can show progress); a filtered
    # download's is not.
    assert int(whole.headers["content-length"]) == len(whole.content) > 1_000_000
    assert "content-length" not in one.headers


@pytest.mark.parametrize("start", [12, 22])
def test_exact_latest_at_keeps_each_components_newest_value(
    tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path], rerun_bin: str, tmp_path: Path, start: int
):
    """A compacted run (`rerun rrd optimize`): chunk [0-9] holds colors only at frames 0-2 and 7 (nulls
    elsewhere), the later chunks none. At `start` the scene's color is frame 7's, and an exact download
    keeps that row, hot and warm alike. start=12: chunk [0-9] is the latest-at chunk of both components;
    start=22: only of colors (positions come from [10-19]), and the warm index has only the chunk's range."""
    node, run_id = _node(make_node, tiers, runs["sparse"])
    client = TestClient(_app(node))
    colors = {t for _, c, t in _cells(_get(client, run_id, {})) if c == "Points3D:colors"}
    assert colors == {0, 1, 2, 7}, colors
    params = {"timeline": "frame", "start": str(start), "end": str(start + 2), "exact": "true"}
    hot = _get(client, run_id, params)
    _promote(node, run_id)
    warm = _get(client, run_id, params)
    _verify(rerun_bin, warm, tmp_path / "warm.rrd")
    newest = ("/world/sparse", "Points3D:colors", 7)
    assert newest in _cells(hot), f"hot: {sorted(_cells(hot))}"
    assert newest in _cells(warm), f"warm: {sorted(_cells(warm))}"
    assert _cells(warm) == _cells(hot)


def test_entity_filters_keep_the_recordings_properties_hot_and_warm(
    tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path]
):
    node, run_id = _node(make_node, tiers, runs["wide"])
    client = TestClient(_app(node))
    cases = [
        ({"include": "/world/e3"}, True),
        ({"exclude": "/world/**"}, True),
        ({"include": "/world/e3", "timeline": "frame", "start": "5", "end": "6"}, True),
        ({"include": "/world/e3", "exclude": "/__properties/**"}, False),
        ({"exclude": "/__properties"}, False),
    ]
    hot = [_get(client, run_id, params) for params, _ in cases]
    _promote(node, run_id)
    for (params, kept), hot_answer in zip(cases, hot, strict=True):
        warm = _get(client, run_id, params)
        for answer in (hot_answer, warm):
            entities = {e for e, _, _ in _chunks(answer)}
            assert ("/__properties" in entities) == kept and entities - {"/__properties"}, (params, entities)
        assert _ids(warm) == _ids(hot_answer), params


def test_filters_that_match_no_entity_are_warned_of_hot_and_warm(
    tiers: Tiers, make_node: NodeFactory, runs: dict[str, Path]
):
    node, run_id = _node(make_node, tiers, runs["wide"])
    client = TestClient(_app(node))
    url = f"/v1/runs/{run_id}/recording.rrd"
    asks = {"include": ["/world/e3", "/nowhere/**"], "exclude": "/world"}  # `/world` is no entity: /world/** was meant

    def warned(params: dict[str, Any]) -> list[str]:
        response = client.get(url, params=params, headers={"Origin": "http://localhost:9090"})  # a web viewer
        assert response.status_code == 200, response.text
        assert "fleet-warnings" in response.headers["access-control-expose-headers"].lower()  # it may read them
        warnings: list[str] = json.loads(response.headers.get("fleet-warnings", "[]"))
        return warnings

    for _ in ("hot", "warm"):
        assert warned(asks) == [
            "include /nowhere/** matches no entity of the run",
            "exclude /world matches no entity of the run (its subtree is /world/**)",
        ]
        assert warned({"include": "/world/e3", "exclude": "/world/**"}) == []
        assert warned({}) == []
        if run_id in node.ingest.runs:
            _promote(node, run_id)
