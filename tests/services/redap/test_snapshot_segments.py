"""Snapshot versions as entries of the catalog protocol (services/redap/snapshots.py), on DuckDB and
Postgres: entry ids made from a version's row alone, `NAME:N` beside the applications (and winning
the name over an application so named), segment ids naming episodes, the segment table of a
version's episodes, missing runs, refused writes; chunk keys and chunks of a window episode; and the
candidate chunks a query of a version finds, the episodes' own."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import lz4.block
import pyarrow as pa
import pytest
from sqlalchemy.orm import sessionmaker

from catalog import datasets as snapshot_rows
from catalog.datasets import EpisodeRecord, VersionFacts
from catalog.db import create_engine, session_scope
from core.errors import ConflictError, InvalidArgumentError, NotFoundError, UnimplementedError
from core.ids import new_entry_id
from services.auth.scopes import Principal, Scope
from services.redap import entries, manifest, query, segments, snapshots
from services.redap.dataframe import read_dataframe_part
from services.redap.depot import Depot
from services.redap.entries import ENTRIES_TABLE_ID
from services.redap.keys import ChunkLocation, chunk_key, episode_chunk_id, parse_chunk_key
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid, epoch_ns
from services.rrd import ArrowMessage, iter_events
from services.rrd.chunk import chunk_meta, with_chunk_id
from services.rrd.layout import split_ipc
from services.rrd.messages import chunk_id_str
from services.rrd.pb import log_msg_pb2
from tests.services.auth.conftest import Depot as AppDepot
from tests.services.auth.conftest import open_depot
from tests.services.datasets.conftest import upload, writer
from tests.services.nodes import node_of
from tests.services.redap.depots import NOW, catalog_depot, entry_of, record, save
from tests.services.redap.golden import EVERYTHING, time_range
from tests.services.redap.golden import segments as segment_selection
from tests.services.rrd.synthetic import recording_bytes

K = cloud_pb2
READER = Principal("alice", frozenset({Scope.READ}), token_id="t1")
MADE = NOW + dt.timedelta(hours=1)
IDS = [bytes([n]) * 16 for n in range(1, 7)]


def _episode(run_id: str, ids: list[bytes], window: tuple[int, int] | None = None) -> EpisodeRecord:
    start, end = window if window is not None else (None, None)
    event = "ev-1" if window is not None else None
    return EpisodeRecord(run_id, "robot-7", "train", "frame", start, end, event, tuple(ids), 100 * len(ids))


def add_version(depot: Depot, name: str, episodes: list[EpisodeRecord], at: dt.datetime = MADE) -> None:
    selection = '{"include":["/world/**"],"exclude":[]}'
    facts = VersionFacts(selection, "alice", at, None, len({e.run_id for e in episodes}), "[]")
    with session_scope(depot.catalog, write=True) as session:
        snapshot_rows.add_version(session, name, facts, episodes)


@pytest.fixture
def depot(fresh_catalog_url: str) -> Iterator[Depot]:
    """Application `nav` (runs nav-1, nav-2: frames 0 to 9); `picks@1`: windows [0, 4] and [5, 9]
    of nav-1 and [2, 3] of nav-2; `whole@1`: both runs whole."""
    with catalog_depot(fresh_catalog_url) as made:
        save(made, record("nav-1"), record("nav-2"))
        add_version(
            made,
            "picks",
            [
                _episode("nav-1", IDS[:3], (0, 4)),
                _episode("nav-1", IDS[:1] + IDS[3:4], (5, 9)),
                _episode("nav-2", IDS[4:], (2, 3)),
            ],
        )
        add_version(
            made, "whole", [_episode("nav-1", IDS[:4]), _episode("nav-2", IDS[4:])], MADE + dt.timedelta(seconds=1)
        )
        yield made


def version_entry(depot: Depot, name: str, number: int = 1) -> Tuid:
    with session_scope(depot.catalog) as session:
        found = snapshot_rows.version(session, name, number)
        assert found is not None
        return snapshots.snapshot_entry_id(name, number, found.created_at)


def find(depot: Depot, **entry_filter: object) -> list[tuple[str, str]]:
    request = K.FindEntriesRequest(filter=K.EntryFilter(**entry_filter))  # type: ignore[arg-type]
    return sorted((e.name, str(Tuid.from_proto(e.id.id))) for e in entries.find_entries(depot, READER, request).entries)


# --- entries -----------------------------------------------------------------------------------


def test_a_version_s_entry_id_comes_from_its_row_alone(depot: Depot, fresh_catalog_url: str, tmp_path: Path):
    picks = version_entry(depot, "picks")
    assert picks.time_ns == epoch_ns(MADE)  # its creation time, then a digest of its ref
    assert str(picks) != new_entry_id("picks:1", epoch_ns(MADE))  # never an application's of that name and time
    engine = create_engine(fresh_catalog_url)  # another node, or this one restarted: nothing kept but the catalog
    try:
        other = Depot(node_of(tmp_path, sessionmaker(engine)), None)
        assert ("picks:1", str(picks)) in find(other, name="picks:1")
        with session_scope(other.catalog) as session:
            found = snapshots.find_dataset(session, picks)
        assert isinstance(found, snapshots.SnapshotVersion) and (found.name, found.version) == ("picks", 1)
    finally:
        engine.dispose()


def test_versions_are_dataset_entries_beside_the_applications(depot: Depot):
    names = [name for name, _ in find(depot, entry_kind=K.ENTRY_KIND_DATASET)]
    assert names == ["nav", "picks:1", "whole:1"]
    (details,) = entries.find_entries(depot, READER, K.FindEntriesRequest(filter=K.EntryFilter(name="whole:1"))).entries
    assert (
        details.created_at.ToDatetime(dt.UTC) == details.updated_at.ToDatetime(dt.UTC) == MADE + dt.timedelta(seconds=1)
    )
    table = [e.name for e in entries.catalog_entries(depot)]
    assert table == ["nav", "picks:1", "whole:1", "__entries"]  # the viewer's server page lists them too
    answer = entries.read_dataset_entry(depot, READER, version_entry(depot, "picks")).dataset
    assert answer.details.name == "picks:1" and answer.dataset_handle.dataset_url == "fleet:///v1/datasets/picks/1"
    assert answer.HasField("dataset_details")


def test_an_application_named_as_a_version_is_keeps_its_id_but_not_the_name(depot: Depot):
    save(depot, record("odd-1", "picks:1"))  # an application id may hold `:`
    application = str(entry_of(depot, "picks:1"))
    version = str(version_entry(depot, "picks"))
    assert find(depot, name="picks:1") == [("picks:1", version)]  # a lookup by name finds the version
    assert sorted(find(depot, entry_kind=K.ENTRY_KIND_DATASET)).count(("picks:1", application)) == 1  # listed beside
    shown = entries.read_dataset_entry(depot, READER, Tuid.parse(application)).dataset
    assert shown.dataset_handle.dataset_url == "fleet:///v1/runs?application=picks%3A1"


def test_an_entry_id_of_no_version_is_not_found(depot: Depot):
    picks = version_entry(depot, "picks")
    for entry in (Tuid(picks.time_ns, picks.inc ^ 1), Tuid(2**64 - 1, 5), Tuid(0, 0)):
        with pytest.raises(NotFoundError, match="FindEntries"):
            entries.read_dataset_entry(depot, READER, entry)


# --- segments ----------------------------------------------------------------------------------


def _version(depot: Depot, name: str) -> snapshots.SnapshotVersion:
    with session_scope(depot.catalog) as session:
        found = snapshots.find_dataset(session, version_entry(depot, name))
    assert isinstance(found, snapshots.SnapshotVersion)
    return found


def test_segment_ids_name_episodes_run_for_a_whole_run_and_run_tilde_n_for_a_window(depot: Depot):
    picks, whole = _version(depot, "picks"), _version(depot, "whole")
    asked = ["nav-1~0", "nav-1~1", "nav-2~2", "nav-1", "nav-2~0", "nav-1~00", "nav-1~x", "nav-1~", "~1", "nav-1~99"]
    with session_scope(depot.catalog) as session:
        assert [e.episode for e in snapshots.episodes_named(session, picks, asked)] == [0, 1, 2]
        assert [snapshots.segment_id_of(e) for e in snapshots.episodes_named(session, whole, asked)] == ["nav-1"]
        assert snapshots.episodes_named(session, whole, ["nav-1~0"]) == []  # one id for each episode
        with pytest.raises(NotFoundError, match=r"no segment 'nav-1'.*RUN~N for episode N"):
            snapshots.episode_of(session, picks, "nav-1")


def _scan(depot: Depot, entry: Tuid, **fields: Any) -> list[dict[str, Any]]:
    found = segments.scan(depot, READER, entry, K.ScanSegmentTableRequest(**fields))
    parts = [read_dataframe_part(r.data) for r in found]
    table = pa.concat_tables(parts)
    table = pa.table(
        [c.cast(pa.int64()) if pa.types.is_temporal(c.type) else c for c in table.columns], names=table.column_names
    )
    rows: list[dict[str, Any]] = table.to_pylist()
    return rows


def test_the_segment_table_of_a_version_is_its_episodes(depot: Depot):
    picks = version_entry(depot, "picks")
    rows = _scan(depot, picks)
    assert [r["rerun_segment_id"] for r in rows] == ["nav-1~0", "nav-1~1", "nav-2~2"]
    first = rows[0]
    assert (first["property:depot:episode"], first["property:depot:run_id"]) == ([0], ["nav-1"])
    assert (first["property:depot:window_start"], first["property:depot:window_end"]) == ([0], [4])
    assert (first["property:depot:split"], first["property:depot:event_id"]) == (["train"], ["ev-1"])
    assert (first["rerun_num_chunks"], first["rerun_size_bytes"]) == (3, 300)
    assert (first["frame:start"], first["frame:end"]) == (0, 4)  # its window, within the run's 0 to 9
    assert first["rerun_last_updated_at"] == epoch_ns(MADE)  # a version never changes
    assert first["rerun_storage_urls"] == ["fleet:///v1/datasets/picks/1/episodes/0/recording.rrd"]
    assert first["property:fleet:robot_id"] == ["robot-7"]  # the run's own properties, as for runs
    only = K.SegmentIdFilter(scan_only=K.SegmentIdList(segment_ids=["nav-2~2", "nope", "nav-2"]))
    assert [r["rerun_segment_id"] for r in _scan(depot, picks, segment_id_filter=only)] == ["nav-2~2"]
    skip = K.SegmentIdFilter(skip=K.SegmentIdList(segment_ids=["nav-1~1"]))
    assert [r["rerun_segment_id"] for r in _scan(depot, picks, segment_id_filter=skip)] == ["nav-1~0", "nav-2~2"]
    whole = _scan(depot, version_entry(depot, "whole"), columns=["rerun_segment_id", "property:depot:window_start"])
    assert whole == [
        {"rerun_segment_id": "nav-1", "property:depot:window_start": None},
        {"rerun_segment_id": "nav-2", "property:depot:window_start": None},
    ]


def test_an_episode_whose_run_is_deleted_or_gone_is_missing(depot: Depot):
    save(depot, record("nav-2"), later={"nav-2": {"tier": "deleted"}})
    add_version(depot, "gone", [_episode("never-held", IDS[:1], (1, 2))], MADE + dt.timedelta(seconds=2))
    rows = {r["rerun_segment_id"]: r for r in _scan(depot, version_entry(depot, "picks"))}
    assert rows["nav-1~0"]["property:depot:missing"] == [False]
    assert rows["nav-2~2"]["property:depot:missing"] == [True]
    assert "which is missing: run deleted" in rows["nav-2~2"]["property:depot:missing_why"][0]
    with pytest.raises(NotFoundError, match=r"segment 'nav-2~2' of picks:1 reads run 'nav-2', which is missing"):
        manifest.find_segment(depot, version_entry(depot, "picks"), "nav-2~2")
    (gone,) = _scan(depot, version_entry(depot, "gone"))
    assert gone["property:depot:tier"] == ["deleted"] and gone["property:depot:robot_id"] == ["robot-7"]
    assert "the catalog no longer has this run" in gone["property:depot:missing_why"][0]


def test_writes_to_a_version_are_refused_it_never_changes(depot: Depot):
    with pytest.raises(ConflictError, match=r"picks:1 \(picks@1\) is a dataset snapshot version, which never changes"):
        entries.refuse_write(depot, READER, version_entry(depot, "picks"), "RegisterWithDataset")
    for entry in (entry_of(depot, "nav"), ENTRIES_TABLE_ID, None, Tuid(1, 2)):
        with pytest.raises(UnimplementedError, match="does not serve DeleteEntry"):
            entries.refuse_write(depot, READER, entry, "DeleteEntry")


# --- chunks of a window ------------------------------------------------------------------------


def test_a_window_s_chunk_key_names_its_segment_and_its_run():
    key = chunk_key("nav-1~3", 100, 50, IDS[0])
    assert parse_chunk_key(key) == ChunkLocation("nav-1", 100, 50, IDS[0], "nav-1~3")
    assert parse_chunk_key(chunk_key("nav-1", 100, 50, IDS[0])) == ChunkLocation("nav-1", 100, 50, IDS[0])
    for bad in ("nav-1~x", "~3", "nav-1~"):
        with pytest.raises(InvalidArgumentError, match="not one this depot handed out"):
            parse_chunk_key(chunk_key(bad, 100, 50, IDS[0]))
    assert episode_chunk_id("nav-1~3", IDS[0]) != episode_chunk_id("nav-1~4", IDS[0]) != IDS[0]
    assert episode_chunk_id("nav-1~3", IDS[0])[:8] == IDS[0][:8]  # the chunk's time stays


def test_a_chunk_renamed_for_a_window_keeps_its_record_batch_byte_for_byte(tmp_path: Path):
    path = tmp_path / "run.rrd"
    path.write_bytes(recording_bytes("run-a", 4))
    message = next(e for e in iter_events(path) if isinstance(e, ArrowMessage) and not e.is_static)
    named = log_msg_pb2.ArrowMsg.FromString(with_chunk_id(bytes(message.raw), IDS[5], "run-a~2"))
    before = lz4.block.decompress(message.payload, uncompressed_size=message.uncompressed_size)
    after = lz4.block.decompress(named.payload, uncompressed_size=named.uncompressed_size)
    old, new = split_ipc(before), split_ipc(after)
    assert old is not None and new is not None
    assert after[new[1] :] == before[old[1] :]  # the record batch, as stored
    assert pa.ipc.read_schema(pa.py_buffer(after[: new[1]])).metadata[b"rerun:id"] == chunk_id_str(IDS[5]).encode()
    assert (named.store_id.recording_id, named.store_id.application_id.id) == (
        "run-a~2",
        message.store_id.application_id,
    )
    again = ArrowMessage(
        0,
        0,
        0,
        named.SerializeToString(),
        message.store_id,
        IDS[5],
        False,
        message.compression,
        len(after),
        named.payload,
    )
    assert chunk_meta(again).chunk_id == IDS[5] and chunk_meta(again).num_rows == chunk_meta(message).num_rows


# --- what a query of a version finds -----------------------------------------------------------


@pytest.fixture
def app_depot(tmp_path: Path, fresh_catalog_url: str) -> Iterator[AppDepot]:
    with open_depot(tmp_path, fresh_catalog_url) as opened:
        yield opened


def _candidates(depot: Depot, entry: Tuid, request: Any) -> pa.Table:
    call = query.find_chunks if isinstance(request, K.FindChunksRequest) else query.query_dataset
    return pa.concat_tables([read_dataframe_part(r.data) for r in call(depot, READER, entry, request)])


def test_a_query_of_a_version_finds_each_episode_s_chunks_and_no_other(app_depot: AppDepot):
    upload(app_depot, "run-a", seal=True)
    upload(app_depot, "run-b")  # hot
    alice = writer(app_depot)
    for run_id, frame in (("run-a", 300), ("run-a", 600), ("run-b", 600)):
        alice.annotate(run_id, "frame", frame, kind="pick")
    alice.create_dataset("picks", event_window={"event": ["pick"], "before_s": 50, "after_s": 20})
    page = alice.dataset_version("picks", 1, chunk_ids=True)["episodes_page"]
    expected = {
        f"{e['run_id']}~{e['index']}": {
            episode_chunk_id(f"{e['run_id']}~{e['index']}", bytes.fromhex(i)) for i in e["chunk_ids"]
        }
        for e in page
    }
    app = app_depot.app
    depot = Depot(app.state.node, app.state.ingest)
    with session_scope(depot.catalog) as session:
        entry = snapshots.snapshot_entry_id("picks", 1, snapshot_rows.version(session, "picks", 1).created_at)  # type: ignore[union-attr]
    found = _candidates(depot, entry, K.FindChunksRequest(contents=EVERYTHING, range=time_range("frame")))
    by_segment: dict[str, set[bytes]] = {}
    for row in found.to_pylist():
        by_segment.setdefault(row["chunk_segment_id"], set()).add(row["chunk_id"])
        assert parse_chunk_key(row["chunk_key"]).episode == row["chunk_segment_id"]
    assert by_segment == expected  # each episode's chunks, by ids of its own, and nothing else of the runs
    named = K.FindChunksRequest(
        contents=EVERYTHING, range=time_range("frame", segments=segment_selection("run-a~1", "run-a"))
    )
    assert set(_candidates(depot, entry, named)["chunk_segment_id"].to_pylist()) == {"run-a~1"}
    narrow = K.FindChunksRequest(
        contents=EVERYTHING, range=time_range("frame", 600, 601, segments=segment_selection("run-a~1"))
    )
    within = set(_candidates(depot, entry, narrow)["chunk_id"].to_pylist())
    assert within and within < expected["run-a~1"]  # a time range narrows within the episode's chunks
    legacy = K.QueryDatasetRequest(
        select_all_entity_paths=True, segment_ids=[{"id": "run-b~2"}]
    )  # SDKs before FindChunks
    assert set(_candidates(depot, entry, legacy)["chunk_id"].to_pylist()) == expected["run-b~2"]
