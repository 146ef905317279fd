"""GetRrdManifest and GetAssetsForSegment against Rerun's own server on the same files.

A sealed run's manifest is its footer's, read by range, plus `chunk_key`: compared with what
`rerun server` answers for the very same `recording.rrd`, it is identical but for the keys (columns,
types, field metadata, values, Sorbet schema and its hash). A hot run's, built from its chunk index,
has the same shape as the manifest Rerun serves for the robot's own file, and the same values but
for byte offsets, which are those of the hot file.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import grpc
import pyarrow as pa
import pytest

from catalog import queries
from catalog.db import session_scope
from services.redap import manifest as manifest_module
from services.redap.keys import parse_chunk_key
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from services.retention import archive
from services.retention.service import promote_now
from services.rrd import iter_events
from services.rrd.frames import MESSAGE_HEADER_SIZE
from services.rrd.manifest import read_manifest, read_sorbet_schema
from services.rrd.messages import ArrowMessage
from services.rrd.pb import common_pb2, log_msg_pb2
from services.sealed.tiers import Tiers
from services.sealed.write import RECORDING
from tests.services.redap.catalog_node import catalog_server, count_reads, entry_of
from tests.services.redap.client import Redap
from tests.services.retention import conftest as retention
from tests.services.retention.conftest import Node, NodeFactory
from tests.services.rrd.recordings import Recording

pytestmark = pytest.mark.sdk
tiers, make_node = retention.tiers, retention.make_node  # the retention tests' stores and nodes

# One SDK-written scene of each kind: plain chunks, compacted (sparse) chunks, a blueprint beside the
# recording, recording properties, several timeline types, 1 MB chunks.
SCENES = ("points", "optimized", "blueprint", "properties", "transforms", "large")
# What the depot stores of a robot's file is the file but for the secrets it strips: the `properties`
# scene sends a token in its `fleet` property, which the depot never keeps.
AS_LOGGED = tuple(s for s in SCENES if s != "properties")
OFFSET_COLUMNS = ("chunk_byte_offset", "chunk_key")


def manifest_request(segment: str) -> cloud_pb2.GetRrdManifestRequest:
    return cloud_pb2.GetRrdManifestRequest(segment_id=common_pb2.SegmentId(id=segment), generate_direct_urls=True)


def reference_entry(client: Redap, name: str) -> str:
    found = client.call("FindEntries", cloud_pb2.FindEntriesRequest())
    return str(Tuid.from_proto(next(e.id.id for e in found.entries if e.name == name)))


def served(client: Redap, entry: str, segment: str) -> tuple[pa.Table, pa.Schema, log_msg_pb2.RrdManifest, int]:
    """(the manifest's rows, its Sorbet schema, the manifest message, how many parts) of a segment."""
    answers = client.call("GetRrdManifest", manifest_request(segment), entry=entry)
    assert answers and all(a.HasField("rrd_manifest") and not a.HasField("manifest_key") for a in answers)
    tables = [read_manifest(a.rrd_manifest) for a in answers]
    first = answers[0].rrd_manifest
    return pa.concat_tables(tables), read_sorbet_schema(first), first, len(answers)


def same_shape(ours: pa.Table, theirs: pa.Table) -> None:
    """Same columns, in the same order, of the same types, with the same field metadata."""
    assert ours.schema.names == theirs.schema.names
    for mine, ref in zip(ours.schema, theirs.schema, strict=True):
        assert mine.equals(ref, check_metadata=True), (mine, mine.metadata, ref, ref.metadata)


def same_values(ours: pa.Table, theirs: pa.Table, but: tuple[str, ...]) -> None:
    for name in ours.schema.names:
        if name not in but:
            assert ours.column(name).equals(theirs.column(name)), name


def recording_id(rec: Recording) -> str:
    return str(rec.recordings[0]["recording_id"])


def application_id(rec: Recording) -> str:
    return str(rec.recordings[0]["application_id"])


def uploaded(make_node: NodeFactory, tiers: Tiers, recs: list[Recording]) -> Node:
    node = make_node(tiers)
    for rec in recs:
        node.upload(rec.path)
    return node


def sealed_copy(node: Node, run_id: str, folder: Path) -> Recording:
    """The run's sealed recording.rrd, as a file Rerun's server can load."""
    with session_scope(node.catalog) as session:
        life = queries.lifecycle(session, run_id)
        assert life is not None
        prefix = life.prefix
    path = folder / f"{run_id}.rrd"
    path.write_bytes(node.tiers.warm.get_range(f"{prefix}/{RECORDING}"))
    return Recording(run_id, path, {})


# `optimized` is `points` compacted (the same recording id): a node of its own.
@pytest.mark.parametrize("scenes", [tuple(s for s in SCENES if s != "optimized"), ("optimized",)])
def test_a_sealed_manifest_is_rerun_servers_answer_for_the_sealed_file_but_for_the_keys(
    make_node: NodeFactory,
    tiers: Tiers,
    recordings: dict[str, Recording],
    reference_server: Callable[[dict[str, list[Recording]]], Redap],
    tmp_path: Path,
    scenes: tuple[str, ...],
):
    recs = [recordings[s] for s in scenes]
    node = uploaded(make_node, tiers, recs)
    for rec in recs:
        promote_now(node.retention, recording_id(rec))
    copies = [sealed_copy(node, recording_id(rec), tmp_path) for rec in recs]
    reference = reference_server({"sealed": copies, "robot": recs})
    sealed_entry, robot_entry = reference_entry(reference, "sealed"), reference_entry(reference, "robot")
    with catalog_server(node) as ours:
        for rec in recs:
            run_id = recording_id(rec)
            table, sorbet, message, parts = served(ours, entry_of(node, application_id(rec)), run_id)
            ref_table, ref_sorbet, ref_message, _ = served(reference, sealed_entry, run_id)
            assert parts == 1
            same_shape(table, ref_table)
            same_values(table, ref_table, but=("chunk_key",))
            assert sorbet.equals(ref_sorbet, check_metadata=True)
            assert list(sorbet) == list(ref_sorbet)
            assert message.sorbet_schema_sha256 == ref_message.sorbet_schema_sha256
            assert message.store_id.recording_id == ref_message.store_id.recording_id == run_id
            assert message.store_id.application_id.id == application_id(rec)  # Rerun's says "none" here
            assert len(set(table.column("chunk_key").to_pylist())) == table.num_rows
            if rec.name not in AS_LOGGED:
                continue
            # And the robot's own file, served by Rerun: the same shape and the same schema hash.
            robot_table, robot_sorbet, robot_message, _ = served(reference, robot_entry, run_id)
            same_shape(table, robot_table)
            assert set(sorbet.names) == set(robot_sorbet.names)
            assert message.sorbet_schema_sha256 == robot_message.sorbet_schema_sha256
            assert sorted(table.column("chunk_id").to_pylist()) == sorted(robot_table.column("chunk_id").to_pylist())


def frames(path: Path) -> dict[bytes, tuple[int, int]]:
    """chunk id -> (offset, length) of its frame, for the recording chunks of a file."""
    return {
        e.chunk_id: (e.offset, MESSAGE_HEADER_SIZE + len(e.raw))
        for e in iter_events(path)
        if isinstance(e, ArrowMessage) and e.chunk_id is not None and not e.store_id.is_blueprint
    }


@pytest.mark.parametrize("tiers", ["file"], indirect=True)  # hot runs: the warm store is not read
@pytest.mark.parametrize("scene", AS_LOGGED)
def test_a_hot_manifest_has_the_shape_rerun_serves_for_the_robots_file(
    make_node: NodeFactory,
    tiers: Tiers,
    recordings: dict[str, Recording],
    reference_server: Callable[[dict[str, list[Recording]]], Redap],
    scene: str,
):
    rec = recordings[scene]
    node = uploaded(make_node, tiers, [rec])
    run_id = recording_id(rec)
    hot_file = node.ingest.runs[run_id].hot.path
    reference = reference_server({"robot": [rec]})
    with catalog_server(node) as ours:
        table, sorbet, message, _ = served(ours, entry_of(node, application_id(rec)), run_id)
    ref_table, ref_sorbet, ref_message, _ = served(reference, reference_entry(reference, "robot"), run_id)
    same_shape(table, ref_table)
    same_values(table, ref_table, but=OFFSET_COLUMNS)
    assert set(sorbet.names) == set(ref_sorbet.names)
    assert sorbet.metadata == ref_sorbet.metadata
    assert message.sorbet_schema_sha256 == ref_message.sorbet_schema_sha256
    # Offsets and keys are those of the hot file's frames.
    where = frames(hot_file)
    for chunk_id, offset, size, key in zip(
        *(table.column(c).to_pylist() for c in ("chunk_id", "chunk_byte_offset", "chunk_byte_size", "chunk_key")),
        strict=True,
    ):
        frame_offset, frame_length = where[chunk_id]
        assert (offset - MESSAGE_HEADER_SIZE, size + MESSAGE_HEADER_SIZE) == (frame_offset, frame_length)
        location = parse_chunk_key(key)
        assert (location.run_id, location.offset, location.length, location.chunk_id) == (
            run_id,
            frame_offset,
            frame_length,
            chunk_id,
        )


def test_a_run_answers_the_same_manifest_hot_and_sealed(
    make_node: NodeFactory, tiers: Tiers, recordings: dict[str, Recording]
):
    rec = recordings["optimized"]
    node = uploaded(make_node, tiers, [rec])
    run_id, entry = recording_id(rec), ""
    with catalog_server(node) as ours:
        entry = entry_of(node, application_id(rec))
        hot, hot_sorbet, hot_message, _ = served(ours, entry, run_id)
        promote_now(node.retention, run_id)
        sealed, sealed_sorbet, sealed_message, _ = served(ours, entry, run_id)
    same_shape(hot, sealed)
    same_values(hot, sealed, but=OFFSET_COLUMNS)
    assert hot_sorbet.equals(sealed_sorbet, check_metadata=True)
    assert hot_message.store_id == sealed_message.store_id
    assert hot_message.sorbet_schema_sha256 == sealed_message.sorbet_schema_sha256


def test_a_sealed_manifest_reads_the_footer_by_range(
    make_node: NodeFactory, tiers: Tiers, recordings: dict[str, Recording], monkeypatch: pytest.MonkeyPatch
):
    rec = recordings["large"]
    node = uploaded(make_node, tiers, [rec])
    run_id = recording_id(rec)
    promote_now(node.retention, run_id)
    reads = count_reads(monkeypatch, node.tiers.warm)
    with catalog_server(node) as ours:
        table, _, _, _ = served(ours, entry_of(node, application_id(rec)), run_id)
    assert table.num_rows > 0
    recording_reads = [r for r in reads if r[0].endswith(RECORDING)]
    assert len(recording_reads) == 2 and all(length is not None for _, _, length in recording_reads)
    size = node.tiers.warm.head(recording_reads[0][0]).size
    assert sum(length or 0 for _, _, length in recording_reads) < size / 50
    assert not [r for r in reads if not r[0].endswith(RECORDING)]  # not even the chunk index


@pytest.mark.parametrize("tiers", ["file"], indirect=True)
def test_a_large_manifest_comes_in_parts_with_one_schema(
    make_node: NodeFactory, tiers: Tiers, recordings: dict[str, Recording], monkeypatch: pytest.MonkeyPatch
):
    rec = recordings["points"]
    node = uploaded(make_node, tiers, [rec])
    run_id = recording_id(rec)
    with catalog_server(node) as ours:
        entry = entry_of(node, application_id(rec))
        whole, _, _, _ = served(ours, entry, run_id)
        monkeypatch.setattr(manifest_module, "PART_BYTES", 2048)
        answers = ours.call("GetRrdManifest", manifest_request(run_id), entry=entry)
    assert len(answers) > 1
    schemas = {a.rrd_manifest.sorbet_schema.arrow_schema for a in answers}
    assert len(schemas) == 1
    assert {a.rrd_manifest.sorbet_schema_sha256 for a in answers} == {answers[0].rrd_manifest.sorbet_schema_sha256}
    parts = [read_manifest(a.rrd_manifest) for a in answers]
    assert all(p.schema.equals(whole.schema, check_metadata=True) for p in parts)
    assert pa.concat_tables(parts).equals(whole)


def expect_error(call: Callable[[], Any], code: grpc.StatusCode, *words: str) -> str:
    with pytest.raises(grpc.RpcError) as info:
        call()
    error: Any = info.value
    assert error.code() == code, error.details()
    for word in words:
        assert word in error.details()
    return str(error.details())


def test_manifest_errors(make_node: NodeFactory, tiers: Tiers, recordings: dict[str, Recording]):
    rec, other = recordings["points"], recordings["transforms"]
    node = uploaded(make_node, tiers, [rec, other])
    run_id = recording_id(rec)
    promote_now(node.retention, run_id)
    archive.archive(run_id, node.tiers, node.catalog, node.clock(), "test")
    with catalog_server(node) as ours:
        entry = entry_of(node, application_id(rec))

        def ask(entry: str, segment: str) -> Callable[[], Any]:
            return lambda: ours.call("GetRrdManifest", manifest_request(segment), entry=entry)

        expect_error(ask(entry, run_id), grpc.StatusCode.FAILED_PRECONDITION, "fleet runs restore", run_id)
        expect_error(ask(entry, "no-such-run"), grpc.StatusCode.NOT_FOUND, "no-such-run")
        # A run of another application is not a segment of this dataset.
        expect_error(ask(entry, recording_id(other)), grpc.StatusCode.NOT_FOUND, recording_id(other))
        expect_error(ask(str(Tuid(1, 2)), run_id), grpc.StatusCode.NOT_FOUND, "FindEntries")
        expect_error(ask(entry, ""), grpc.StatusCode.INVALID_ARGUMENT, "segment")
        # The server goes on answering.
        table, _, _, _ = served(ours, entry_of(node, application_id(other)), recording_id(other))
        assert table.num_rows > 0


@pytest.mark.parametrize("tiers", ["file"], indirect=True)
def test_assets_are_an_empty_answer(
    make_node: NodeFactory,
    tiers: Tiers,
    recordings: dict[str, Recording],
    reference_server: Callable[[dict[str, list[Recording]]], Redap],
):
    rec = recordings["points"]
    node = uploaded(make_node, tiers, [rec])
    run_id = recording_id(rec)
    request = cloud_pb2.GetAssetsForSegmentRequest(segment_id=common_pb2.SegmentId(id=run_id))
    reference = reference_server({"robot": [rec]})
    theirs = reference.call("GetAssetsForSegment", request, entry=reference_entry(reference, "robot"))
    # Rerun's server names an (empty) asset dataset; with no assets at all, no answer says the same.
    assert [list(a.asset_segment_ids) for a in theirs] == [[]]
    with catalog_server(node) as ours:
        entry = entry_of(node, application_id(rec))
        assert ours.call("GetAssetsForSegment", request, entry=entry) == []
        assert ours.call("GetAssetsForSegment", cloud_pb2.GetAssetsForSegmentRequest(), entry=entry) == []
        missing = cloud_pb2.GetAssetsForSegmentRequest(segment_id=common_pb2.SegmentId(id="nope"))
        expect_error(lambda: ours.call("GetAssetsForSegment", missing, entry=entry), grpc.StatusCode.NOT_FOUND)
        expect_error(
            lambda: ours.call("GetAssetsForSegment", request, entry=str(Tuid(1, 2))), grpc.StatusCode.NOT_FOUND
        )


@pytest.mark.parametrize("tiers", ["file"], indirect=True)
def test_the_manifest_names_the_chunks_the_file_holds(
    make_node: NodeFactory, tiers: Tiers, recordings: dict[str, Recording]
):
    """A blueprint's chunks are not the recording's: the manifest lists only the recording store."""
    rec = recordings["blueprint"]
    node = uploaded(make_node, tiers, [rec])
    run_id = recording_id(rec)
    recording_chunks = {
        e.chunk_id for e in iter_events(rec.path) if isinstance(e, ArrowMessage) and not e.store_id.is_blueprint
    }
    with catalog_server(node) as ours:
        table, _, _, _ = served(ours, entry_of(node, application_id(rec)), run_id)
    assert set(table.column("chunk_id").to_pylist()) == recording_chunks
