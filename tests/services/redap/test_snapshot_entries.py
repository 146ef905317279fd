"""Dataset snapshot versions in the catalog protocol, through the real rerun-sdk `CatalogClient`: a
robot's two runs (the real SDK, one sealed, one hot) with people's events on them, a snapshot of
windows around those events (`picks:1`, two windows on one run) and one of whole runs (`whole:1`).

Each version is a dataset entry named `NAME@N`; its segment table lists its episodes; a dataframe
query over it returns exactly the rows of each episode's chunks, the rows Rerun's own reader finds in
those chunks of the robot's file (read with `rr.chunk.RrdReader`, the chunks filtered by the ids the
version lists); a whole-run episode returns its run's rows; writes are refused; and an episode whose
run was deleted since answers NOT_FOUND saying so, while a query over every segment reads the rest."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import pyarrow as pa
import pyarrow.compute as pc
import pytest

from catalog import datasets as snapshot_rows
from catalog.db import session_scope
from services.redap.depot import Depot as CatalogDepot
from services.redap.keys import episode_chunk_id
from services.redap.pb import cloud_pb2
from services.redap.snapshots import snapshot_entry_id
from services.redap.tuid import Tuid
from services.rrd import ArrowMessage, iter_events
from tests.conftest import CATALOG_KINDS, fresh_catalog
from tests.services.auth.conftest import Depot, bearer, open_depot
from tests.services.datasets.conftest import writer
from tests.services.redap.catalog_node import BigRedap, CatalogGrpc
from tests.services.redap.test_reader_e2e import DATASET, _comparable, _log_robot, _window

pytestmark = pytest.mark.sdk

RUN_A, RUN_B = "snap-run-a", "snap-run-b"  # A sealed, B hot
ROBOT = "robot-e2e"  # what the robot's files say (their `fleet` property)
WINDOW = {"event": ["pick"], "before_s": 5, "after_s": 3}  # frames: 5 steps before, 3 after


@pytest.fixture(scope="module")
def robot_files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("snapshot-robot")
    return {
        RUN_A: _log_robot(folder / f"{RUN_A}.rrd", RUN_A, 40),
        RUN_B: _log_robot(folder / f"{RUN_B}.rrd", RUN_B, 50),
    }


@dataclass
class Scene:
    depot: Depot
    server: CatalogGrpc
    files: dict[str, Path]

    @property
    def url(self) -> str:
        return f"rerun+http://127.0.0.1:{self.server.port}"

    def client(self) -> Any:
        import rerun as rr

        return rr.catalog.CatalogClient(self.url, token=self.depot.token("read", name="analyst"))

    def episodes(self, name: str) -> dict[str, dict[str, Any]]:
        """segment id -> the episode as REST shows it (with its chunk ids)."""
        page = writer(self.depot).dataset_version(name, 1, limit=1000, chunk_ids=True)
        return {_segment(e): e for e in page["episodes_page"]}


def _segment(episode: dict[str, Any]) -> str:
    return episode["run_id"] if episode["start"] is None else f"{episode['run_id']}~{episode['index']}"


def upload(depot: Depot, path: Path, run_id: str, *, seal: bool) -> None:
    answer = depot.client.post(
        "/v1/uploads", content=path.read_bytes(), headers=bearer(depot.token("ingest", robot=ROBOT))
    )
    assert answer.status_code == 200 and answer.json()["runs"] == [run_id], answer.text
    if seal:
        sealed = depot.client.post(f"/v1/runs/{run_id}/promote", headers=bearer(depot.token("write")))
        assert sealed.status_code == 200 and sealed.json()["tier"] == "warm", sealed.text


@contextmanager
def serving(depot: Depot) -> Iterator[CatalogGrpc]:
    """The depot's catalog server (its node and ingest, auth on) on a port of its own."""
    app = depot.app
    server = CatalogGrpc(CatalogDepot(app.state.node, app.state.ingest), auth=depot.auth)
    server.start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="module", params=CATALOG_KINDS)
def scene(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory, robot_files: dict[str, Path]
) -> Iterator[Scene]:
    """Run A sealed, run B hot; picks at frames 12 and 30 of A and 20 of B; `picks:1` their windows,
    `whole:1` the two runs whole. Tests only read it."""
    root = tmp_path_factory.mktemp("snapshot-depot")
    with fresh_catalog(request.param, request, root) as url, open_depot(root, url) as depot:
        upload(depot, robot_files[RUN_A], RUN_A, seal=True)
        upload(depot, robot_files[RUN_B], RUN_B, seal=False)
        alice = writer(depot)
        for run_id, frame in ((RUN_A, 12), (RUN_A, 30), (RUN_B, 20)):
            alice.annotate(run_id, "frame", frame, kind="pick")
        assert alice.create_dataset("picks", event_window=WINDOW)["episodes"] == 3
        assert alice.create_dataset("whole", application=[DATASET])["episodes"] == 2
        with serving(depot) as server:
            yield Scene(depot, server, robot_files)


def _episode_rows(path: Path, chunk_ids: list[str], **reader: Any) -> pa.Table:
    """Rerun's own reader over the chunks of the robot's file that the episode lists."""
    import rerun as rr

    wanted = set(chunk_ids)
    chunks = [c for c in rr.chunk.RrdReader(path).stream() if c.id.removeprefix("chunk_").lower() in wanted]
    assert len(chunks) == len(wanted), "the episode lists chunks of the robot's file"
    return rr.chunk.ChunkStore.from_chunks(chunks).reader("frame", **reader).to_arrow_table()


def _whole_rows(path: Path) -> pa.Table:
    import rerun as rr

    return rr.chunk.RrdReader(path).stream().collect().reader("frame").to_arrow_table()


def _pylist(table: pa.Table) -> list[dict[str, Any]]:
    """The rows, times as integers (nanosecond timestamps do not fit Python's datetime)."""
    columns = [c.cast(pa.int64()) if pa.types.is_temporal(c.type) else c for c in table.columns]
    rows: list[dict[str, Any]] = pa.table(columns, names=table.column_names).to_pylist()
    return rows


def _of(found: pa.Table, segment: str) -> pa.Table:
    return found.filter(pc.equal(found["rerun_segment_id"], segment))


# --- the entries -----------------------------------------------------------------------------------


def test_each_version_is_a_dataset_entry_named_name_at_n(scene: Scene):
    client = scene.client()
    assert {"picks:1", "whole:1", DATASET} <= set(client.dataset_names())
    picks = client.get_dataset("picks:1")
    with session_scope(scene.depot.app.state.catalog) as session:
        version = snapshot_rows.version(session, "picks", 1)
        assert version is not None
        made = snapshot_entry_id("picks", 1, version.created_at)
    assert str(picks.id) == str(made)  # from the version's row alone: the same on every node, after restarts
    assert client.get_dataset(id=str(made)).name == "picks:1"
    assert picks.schema().index_columns()  # its schema is its runs' (GetDatasetSchema)


def test_the_segment_table_lists_the_episodes_with_their_facts(scene: Scene):
    client = scene.client()
    episodes = scene.episodes("picks")
    assert sorted(episodes) == [f"{RUN_A}~0", f"{RUN_A}~1", f"{RUN_B}~2"]  # windows: RUN~N
    table = client.get_dataset("picks:1").segment_table().to_arrow_table()
    application = client.get_dataset(DATASET).segment_table().to_arrow_table()
    rerun = [f for f in application.schema if f.name.startswith("rerun_")]
    assert [f for f in table.schema if f.name.startswith("rerun_")] == rerun  # Rerun's columns as for runs
    rows = {r["rerun_segment_id"]: r for r in _pylist(table)}
    assert sorted(rows) == sorted(episodes)
    for segment, episode in episodes.items():
        row = rows[segment]
        assert row["property:depot:episode"] == [episode["index"]]
        assert row["property:depot:run_id"] == [episode["run_id"]]
        assert row["property:depot:timeline"] == ["frame"]
        assert (row["property:depot:window_start"], row["property:depot:window_end"]) == (
            [episode["start"]],
            [episode["end"]],
        )
        assert row["property:depot:event_id"] == [episode["event_id"]]
        assert row["property:depot:missing"] == [False] and row["property:depot:missing_why"] is None
        assert row["property:depot:robot_id"] == [ROBOT]
        assert row["property:fleet:robot_id"] == [ROBOT]  # the run's own properties, as for runs
        assert (row["rerun_num_chunks"], row["rerun_size_bytes"]) == (episode["chunks"], episode["bytes"])
        assert (row["frame:start"], row["frame:end"]) == (episode["start"], episode["end"])  # its window
        assert row["rerun_storage_urls"][0].endswith(f"/v1/datasets/picks/1/episodes/{episode['index']}/recording.rrd")
    assert rows[f"{RUN_A}~0"]["property:depot:tier"] == ["warm"] and rows[f"{RUN_B}~2"]["property:depot:tier"] == [
        "hot"
    ]
    ranges = client.get_dataset("picks:1").get_index_ranges().to_arrow_table()  # what Rerun's dataloader samples
    assert {r["rerun_segment_id"]: (r["frame:start"], r["frame:end"]) for r in _pylist(ranges)} == {
        s: (e["start"], e["end"]) for s, e in episodes.items()
    }


# --- reading -------------------------------------------------------------------------------------


def test_a_query_returns_exactly_the_rows_of_each_episodes_chunks(scene: Scene):
    episodes = scene.episodes("picks")
    client = scene.client()  # outlives the dataframes: they read through it
    found = client.get_dataset("picks:1").reader(index="frame").to_arrow_table()
    assert sorted(set(found["rerun_segment_id"].to_pylist())) == sorted(episodes)
    for segment, episode in episodes.items():
        ours = _of(found, segment)
        path = scene.files[episode["run_id"]]
        assert _comparable(ours) == _comparable(_episode_rows(path, episode["chunk_ids"])), segment
        frames = set(ours["frame"].to_pylist())
        whole = set(_whole_rows(path)["frame"].to_pylist())
        assert frames < whole  # not the run: the chunks around the window, and the scene before it
        assert set(range(episode["start"], episode["end"] + 1)) <= frames


def test_segment_content_and_time_filters_read_within_the_episode(scene: Scene):
    episodes = scene.episodes("picks")
    segment = f"{RUN_A}~1"
    episode = episodes[segment]
    contents = ["/robot/battery", "/world/robot/**"]
    client = scene.client()
    chosen = client.get_dataset("picks:1").filter_segments([segment]).filter_contents(contents)
    path = scene.files[RUN_A]
    found = chosen.reader(index="frame").to_arrow_table()
    assert set(found["rerun_segment_id"].to_pylist()) == {segment}
    assert _comparable(found) == _comparable(_episode_rows(path, episode["chunk_ids"], contents=contents))
    window = _window(episode["start"], episode["end"] + 1)  # latest-at fill from the episode's own chunks
    filled = window(chosen.reader(index="frame", fill_latest_at=True)).to_arrow_table()
    expected = window(_local_frame(path, episode["chunk_ids"], contents))
    assert _comparable(filled) == _comparable(expected.to_arrow_table())


def _local_frame(path: Path, chunk_ids: list[str], contents: list[str]) -> Any:
    import rerun as rr

    wanted = set(chunk_ids)
    chunks = [c for c in rr.chunk.RrdReader(path).stream() if c.id.removeprefix("chunk_").lower() in wanted]
    return rr.chunk.ChunkStore.from_chunks(chunks).reader("frame", contents=contents, fill_latest_at=True)


def test_a_whole_run_episode_returns_the_runs_rows(scene: Scene):
    episodes = scene.episodes("whole")
    assert sorted(episodes) == [RUN_A, RUN_B]  # a whole run's segment id is its run id
    client = scene.client()
    found = client.get_dataset("whole:1").reader(index="frame").to_arrow_table()
    for run_id, path in scene.files.items():
        assert _comparable(_of(found, run_id)) == _comparable(_whole_rows(path)), run_id


def test_the_manifest_and_chunks_of_an_episode_are_its_own(scene: Scene):
    """GetRrdManifest lists the episode's chunks, by ids of its own, its store id naming the segment;
    FetchChunks sends each under that segment and id, its record batch the stored one, a chunk two
    episodes share once for each (Rerun's clients keep one chunk per id over a query's segments)."""
    episodes = scene.episodes("picks")
    entry = str(Tuid.from_proto(_entry(scene, "picks:1")))
    stored = _stored_chunks(scene.files[RUN_A])
    redap = BigRedap(scene.server.port, token=scene.depot.token("read"))
    try:
        keys: dict[str, list[bytes]] = {}
        own: dict[str, dict[bytes, bytes]] = {}  # segment -> its id of a chunk -> the chunk's id
        for segment in (f"{RUN_A}~0", f"{RUN_A}~1"):
            own[segment] = {
                episode_chunk_id(segment, bytes.fromhex(i)): bytes.fromhex(i) for i in episodes[segment]["chunk_ids"]
            }
            request = cloud_pb2.GetRrdManifestRequest(segment_id={"id": segment})
            (answer,) = redap.call("GetRrdManifest", request, entry=entry)
            assert answer.rrd_manifest.store_id.recording_id == segment
            table = pa.ipc.open_stream(_lz4(answer.rrd_manifest.data)).read_all()
            assert sorted(table["chunk_id"].to_pylist()) == sorted(own[segment])
            keys[segment] = table["chunk_key"].to_pylist()
        shared = set(episodes[f"{RUN_A}~0"]["chunk_ids"]) & set(episodes[f"{RUN_A}~1"]["chunk_ids"])
        assert shared  # the static chunks at least
        both = pa.table({"chunk_key": pa.array([k for ks in keys.values() for k in ks], pa.binary())})
        sink = pa.BufferOutputStream()
        with pa.ipc.new_stream(sink, both.schema) as out:
            out.write_table(both)
        part = {"encoder_version": 1, "payload": sink.getvalue().to_pybytes(), "compression": 1}
        fetched = redap.call("FetchChunks", cloud_pb2.FetchChunksRequest(chunk_infos=[part]), timeout=60)
        sent: dict[str, list[bytes]] = {}
        for response in fetched:
            for message in response.chunks:
                segment = message.store_id.recording_id
                chunk_id = bytes.fromhex(_tuid_hex(message.chunk_id))
                sent.setdefault(segment, []).append(chunk_id)
                batch = pa.ipc.open_stream(_lz4(message)).read_all()
                assert batch.schema.metadata[b"rerun:id"].decode().lower().endswith(chunk_id.hex())
                assert batch.equals(stored[own[segment][chunk_id]], check_metadata=False)
        assert {s: sorted(ids) for s, ids in sent.items()} == {s: sorted(ids) for s, ids in own.items()}
    finally:
        redap.close()


def _stored_chunks(path: Path) -> dict[bytes, pa.Table]:
    """The robot file's chunks by id, as tables."""
    found = {}
    for event in iter_events(path):
        if isinstance(event, ArrowMessage) and event.chunk_id is not None:
            found[event.chunk_id] = pa.ipc.open_stream(_lz4(event)).read_all()
    return found


def _entry(scene: Scene, name: str) -> Any:
    redap = BigRedap(scene.server.port, token=scene.depot.token("read"))
    try:
        request = cloud_pb2.FindEntriesRequest(filter=cloud_pb2.EntryFilter(name=name))
        (found,) = redap.call("FindEntries", request).entries
        return found.id.id
    finally:
        redap.close()


def _lz4(part: Any) -> bytes:
    """A dataframe part's or an Arrow message's payload, decompressed."""
    import lz4.block

    if int(part.compression) == 2:
        return bytes(lz4.block.decompress(part.payload, uncompressed_size=part.uncompressed_size))
    return bytes(part.payload)


def _tuid_hex(tuid: Any) -> str:
    return f"{tuid.time_ns:016x}{tuid.inc:016x}"


# --- writes and auth -----------------------------------------------------------------------------


def test_writes_to_a_version_are_refused_it_never_changes(scene: Scene):
    client = scene.client()
    picks = client.get_dataset("picks:1")
    for write in (
        lambda: picks.register(["file:///tmp/other.rrd"]),
        lambda: picks.set_name("renamed"),
        lambda: picks.delete(),
    ):
        with pytest.raises(Exception, match=r"picks:1 \(picks@1\) is a dataset snapshot version, which never changes"):
            write()
    assert "picks:1" in scene.client().dataset_names()
    entry = str(Tuid.from_proto(_entry(scene, "picks:1")))
    channel = grpc.insecure_channel(f"127.0.0.1:{scene.server.port}")
    try:
        delete = channel.unary_unary("/rerun.cloud.v1alpha1.RerunCloudService/DeleteEntry")
        read = [("authorization", f"Bearer {scene.depot.token('read')}")]
        with pytest.raises(grpc.RpcError) as refused:
            delete(b"", metadata=[*read, ("x-rerun-entry-id", entry)], timeout=30)
        assert refused.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        assert "fleet datasets create picks" in (refused.value.details() or "")
        body = cloud_pb2.ReadTableEntryRequest(id={"id": Tuid.parse(entry).to_proto()}).SerializeToString()
        with pytest.raises(grpc.RpcError) as by_body:  # an older client names the entry in the body
            delete(body, metadata=read, timeout=30)
        assert by_body.value.code() == grpc.StatusCode.FAILED_PRECONDITION
        with pytest.raises(grpc.RpcError) as anonymous:
            delete(b"", metadata=[("x-rerun-entry-id", entry)], timeout=30)
        assert anonymous.value.code() == grpc.StatusCode.UNAUTHENTICATED
    finally:
        channel.close()


def test_a_version_is_read_with_the_read_scope(scene: Scene):
    entry = str(Tuid.from_proto(_entry(scene, "picks:1")))
    request = cloud_pb2.GetRrdManifestRequest(segment_id={"id": f"{RUN_A}~0"})
    for token, code in (
        (None, grpc.StatusCode.UNAUTHENTICATED),
        (scene.depot.token("ingest", robot=ROBOT), grpc.StatusCode.PERMISSION_DENIED),
    ):
        redap = BigRedap(scene.server.port, token=token)
        try:
            with pytest.raises(grpc.RpcError) as refused:
                redap.call("GetRrdManifest", request, entry=entry)
            assert refused.value.code() == code
        finally:
            redap.close()


# --- a run deleted since -------------------------------------------------------------------------


def test_an_episode_of_a_deleted_run_is_missing_and_the_rest_reads(
    tmp_path: Path, fresh_catalog_url: str, robot_files: dict[str, Path]
):
    with open_depot(tmp_path, fresh_catalog_url) as depot:
        upload(depot, robot_files[RUN_A], RUN_A, seal=True)
        upload(depot, robot_files[RUN_B], RUN_B, seal=True)
        writer(depot).create_dataset("kept", application=[DATASET])
        deleted = depot.client.delete(
            f"/v1/runs/{RUN_B}", params={"force": "true"}, headers=bearer(depot.token("admin"))
        )
        assert deleted.status_code == 200, deleted.text
        with serving(depot) as server:
            scene = Scene(depot, server, robot_files)
            client = scene.client()
            kept = client.get_dataset("kept:1")
            rows = {r["rerun_segment_id"]: r for r in _pylist(kept.segment_table().to_arrow_table())}
            assert rows[RUN_B]["property:depot:missing"] == [True]
            assert "deleted" in rows[RUN_B]["property:depot:missing_why"][0]
            assert rows[RUN_A]["property:depot:missing"] == [False]
            found = kept.reader(index="frame").to_arrow_table()  # every segment: the one still held
            assert set(found["rerun_segment_id"].to_pylist()) == {RUN_A}
            assert _comparable(_of(found, RUN_A)) == _comparable(_whole_rows(robot_files[RUN_A]))
            with pytest.raises(Exception, match=r"missing: run deleted"):
                kept.filter_segments([RUN_B]).reader(index="frame").to_arrow_table()
            entry = str(kept.id)
            redap = BigRedap(server.port, token=depot.token("read"))
            try:
                with pytest.raises(grpc.RpcError) as gone:
                    redap.call("GetRrdManifest", cloud_pb2.GetRrdManifestRequest(segment_id={"id": RUN_B}), entry=entry)
                assert gone.value.code() == grpc.StatusCode.NOT_FOUND
                assert f"segment '{RUN_B}' of kept:1 reads run '{RUN_B}', which is missing: run deleted" in (
                    gone.value.details() or ""
                )
            finally:
                redap.close()
