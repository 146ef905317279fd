"""GetDatasetSchema, FindChunks and QueryDataset against Rerun's own server (`rerun server` 0.41) on
the same recordings: the same columns, types and metadata; candidate chunks that cover the
reference's (a superset); and where we answer fewer chunks than the reference (latest-at fill and
component selection are pushed down further), that what we answer is enough: Rerun's own
dataframe reader over our candidates alone gives the rows it gives over the whole run.

Recordings are written by the real SDK, uploaded into an in-process depot node and sealed; the
reference server loads the files as written."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import grpc
import pyarrow as pa
import pytest

from catalog import queries
from catalog.db import session_scope
from services.redap import candidate_table
from services.redap.dataframe import read_dataframe_part
from services.redap.keys import parse_chunk_key
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from services.retention.service import ARCHIVE, plan, run_plan
from services.rrd.pb import common_pb2, log_msg_pb2
from tests.services.redap.client import Redap
from tests.services.redap.golden import (  # noqa: F401 - the two *_fixture are fixtures of this module
    ALL,
    EVERYTHING,
    SECRET_COLUMN,
    Servers,
    entities,
    keep_chunks,
    reader_rows,
    recordings_fixture,
    segments,
    servers_fixture,
    table,
    time_range,
)
from tests.services.redap.serving import CatalogServerThread, DepotNode, build_node
from tests.services.runs.latest_at_scenes import RECORDING_IDS

pytestmark = pytest.mark.sdk

# --- GetDatasetSchema ---------------------------------------------------------------------------


def _schema(response: cloud_pb2.GetDatasetSchemaResponse) -> pa.Schema:
    return pa.ipc.read_schema(pa.py_buffer(response.schema.arrow_schema))


@pytest.mark.parametrize("dataset", ["fleet_points", "fleet_scalars", "fleet_static", "fleet_props", "fleet_tf"])
def test_a_run_s_schema_is_the_reference_s_field_for_field_in_order(servers: Servers, dataset: str):
    reference, ours = (
        _schema(r) for r in servers.both("GetDatasetSchema", dataset, cloud_pb2.GetDatasetSchemaRequest())
    )
    if SECRET_COLUMN in reference.names:
        reference = reference.remove(reference.get_field_index(SECRET_COLUMN))
    assert ours.names == reference.names
    assert ours.equals(reference, check_metadata=True), (ours.to_string(), reference.to_string())
    assert ours.metadata is None  # as Rerun answers: no schema-level metadata


@pytest.mark.parametrize(
    ("dataset", "runs"), [("fleet_merge", ["merge_a", "merge_b"]), ("fleet-latest-at", ["per_call", "batched"])]
)
def test_a_dataset_s_schema_merges_its_runs_in_run_order(servers: Servers, dataset: str, runs: list[str]):
    request = cloud_pb2.GetDatasetSchemaRequest()
    reference, ours = (_schema(r) for r in servers.both("GetDatasetSchema", dataset, request))
    # Rerun's server merges its segments in hash-map order: the same fields, any order of runs
    assert sorted(ours.names) == sorted(reference.names)
    for field in reference:
        assert ours.field(field.name).equals(field, check_metadata=True), field.name
    # ours merges them by run id: each run's fields in Rerun's order, a field where it first appears
    by_id = sorted(runs, key=lambda name: _recording_id(servers, name))
    singles = [
        _schema(servers.reference.call("GetDatasetSchema", request, entry=servers.reference_ids[f"one-{name}"]))
        for name in by_id
    ]
    expected: list[str] = []
    for single in singles:
        expected += [n for n in single.names if n not in expected]
    assert ours.names == expected


def _recording_id(servers: Servers, name: str) -> str:
    if name in RECORDING_IDS:
        return RECORDING_IDS[name]
    return {"merge_a": "rec-merge-a", "merge_b": "rec-merge-b"}[name]


# --- candidate columns --------------------------------------------------------------------------


def test_find_chunks_columns_are_the_reference_s(servers: Servers):
    request = cloud_pb2.FindChunksRequest(contents=EVERYTHING, range=time_range("frame"))
    reference, ours = (table(r) for r in servers.both("FindChunks", "fleet_points", request))
    assert ours.schema.equals(reference.schema, check_metadata=True), (ours.schema, reference.schema)
    assert ours.schema.field("rerun_layer_direct_url").type == pa.dictionary(pa.int32(), pa.utf8())
    # no direct URLs: the client fetches with FetchChunks
    assert ours.column("rerun_layer_direct_url").null_count == ours.num_rows > 0


@pytest.mark.parametrize(
    "scan",
    [
        {},
        {"scan_parameters": common_pb2.ScanParameters(columns=["chunk_id", "frame:start"])},
        {"scan_parameters": common_pb2.ScanParameters(columns=["frame:start", "sim:start"])},  # two: none
        {
            "query": cloud_pb2.Query(
                range=cloud_pb2.QueryRange(
                    index=common_pb2.IndexColumnSelector(timeline=common_pb2.Timeline(name="sim")),
                    index_range=common_pb2.TimeRange(start=0, end=10**9),
                )
            )
        },
    ],
    ids=["plain", "start-column-by-name", "two-start-columns", "range-query"],
)
def test_query_dataset_columns_are_the_reference_s(servers: Servers, scan: dict[str, Any]):
    request = cloud_pb2.QueryDatasetRequest(select_all_entity_paths=True, **scan)
    reference, ours = (table(r) for r in servers.both("QueryDataset", "fleet_points", request))
    assert ours.schema.equals(reference.schema, check_metadata=True), (ours.schema, reference.schema)
    starts = [c for c in reference.column_names if c.endswith(":start")]
    for name in starts:  # each chunk's first time on the timeline, null for static chunks
        assert dict(zip(ours["chunk_id"].to_pylist(), ours[name].to_pylist(), strict=True)) == dict(
            zip(reference["chunk_id"].to_pylist(), reference[name].to_pylist(), strict=True)
        )


# --- candidates ---------------------------------------------------------------------------------

# (label, dataset, request): answered with at least the reference's chunks
COVERING = [
    ("all-frame", "fleet_points", {"contents": EVERYTHING, "range": time_range("frame")}),
    ("all-sim", "fleet_points", {"contents": EVERYTHING, "range": time_range("sim")}),
    ("static", "fleet_points", {"contents": EVERYTHING, "static": cloud_pb2.StaticSelection(segments=ALL)}),
    ("static-mixed", "fleet_static", {"contents": EVERYTHING, "static": cloud_pb2.StaticSelection(segments=ALL)}),
    ("range-101-103", "fleet_points", {"contents": EVERYTHING, "range": time_range("frame", 101, 103)}),
    ("range-from-104", "fleet_points", {"contents": EVERYTHING, "range": time_range("frame", 104)}),
    ("range-until-101", "fleet_points", {"contents": EVERYTHING, "range": time_range("frame", None, 101)}),
    ("range-out-of-order", "fleet_scalars", {"contents": EVERYTHING, "range": time_range("step", 2, 6)}),
    (
        "range-timestamps",
        "fleet_tf",
        {"contents": EVERYTHING, "range": time_range("wall", 0, 1_700_000_001_000_000_000)},
    ),
    ("one-entity", "fleet_points", {"contents": entities("/world/sparse"), "range": time_range("frame")}),
    ("entity-no-slash", "fleet_points", {"contents": entities("world/points"), "range": time_range("frame", 102, 104)}),
    ("unknown-entity", "fleet_points", {"contents": entities("/nope"), "range": time_range("frame")}),
    ("timeline-of-one-run", "fleet_merge", {"contents": EVERYTHING, "range": time_range("frame", 0, 1)}),
    (
        "one-segment",
        "fleet_merge",
        {"contents": EVERYTHING, "range": time_range("tick", segments=segments("rec-merge-b"))},
    ),
    (
        "unknown-segment",
        "fleet_merge",
        {"contents": EVERYTHING, "range": time_range("tick", segments=segments("nope"))},
    ),
    ("samples", "fleet_points", {"contents": EVERYTHING, "samples": None}),
    ("two-segments", "fleet-latest-at", {"contents": EVERYTHING, "range": time_range("frame", 30, 60)}),
]


def _samples(
    segment: str, times: list[int], fill: cloud_pb2.FillMode = cloud_pb2.FILL_MODE_NONE
) -> cloud_pb2.SegmentSamplesSelection:
    return cloud_pb2.SegmentSamplesSelection(
        timeline="frame",
        fill_mode=fill,
        segments=[cloud_pb2.SegmentSamples(segment_id=common_pb2.SegmentId(id=segment), values=times)],
    )


def _request(fields: dict[str, Any]) -> cloud_pb2.FindChunksRequest:
    if "samples" in fields and fields["samples"] is None:
        fields = {**fields, "samples": _samples("rec-points", [102, 104])}
    return cloud_pb2.FindChunksRequest(**fields)


def _rows(found: pa.Table) -> dict[bytes, dict[str, Any]]:
    return {r["chunk_id"]: r for r in found.drop(["chunk_key"]).to_pylist()}


@pytest.mark.parametrize(("label", "dataset", "fields"), COVERING, ids=[c[0] for c in COVERING])
def test_candidates_cover_the_reference_s(servers: Servers, label: str, dataset: str, fields: dict[str, Any]):
    reference, ours = (table(r) for r in servers.both("FindChunks", dataset, _request(fields)))
    assert ours.schema.equals(reference.schema, check_metadata=True)
    theirs, mine = _rows(reference), _rows(ours)
    assert set(theirs) <= set(mine), f"{label}: missing {len(set(theirs) - set(mine))} of {len(theirs)}"
    for chunk_id, row in theirs.items():  # the same facts of each chunk (the reference counts sizes its way)
        ignore = {"chunk_byte_len"} | (
            {"chunk_byte_size_uncompressed"} if row["chunk_entity_path"] == "/__properties/fleet" else set()
        )
        assert {k: v for k, v in mine[chunk_id].items() if k not in ignore} == {
            k: v for k, v in row.items() if k not in ignore
        }


def test_chunk_keys_name_each_chunk_s_frame_in_the_sealed_recording(servers: Servers):
    request = cloud_pb2.FindChunksRequest(contents=EVERYTHING, range=time_range("frame"))
    ours = table(servers.ours.call("FindChunks", request, entry=servers.our_ids["fleet_points"]))
    with session_scope(servers.node.catalog) as session:
        life = queries.lifecycle(session, "rec-points")
        assert life is not None
        recording = f"{life.prefix}/recording.rrd"
    for row in ours.to_pylist():
        where = parse_chunk_key(row["chunk_key"])
        assert where.run_id == "rec-points"
        frame = servers.node.tiers.warm.get_range(recording, where.offset, where.length)
        # the whole frame: its 16-byte header (kind 2, ArrowMsg), then chunk_byte_len bytes of message
        assert int.from_bytes(frame[:8], "little") == 2
        assert int.from_bytes(frame[8:16], "little") == row["chunk_byte_len"] == len(frame) - 16
        message = log_msg_pb2.ArrowMsg.FromString(frame[16:])
        assert Tuid.from_proto(message.chunk_id).to_bytes() == row["chunk_id"]
        assert message.uncompressed_size == row["chunk_byte_size_uncompressed"]


# --- enough chunks where we answer fewer than the reference -------------------------------------

# (label, dataset, request fields, {recording: reader arguments}): each recording's rows, read by
# Rerun's own dataframe reader from our candidates alone, are those it reads from the whole file
ENOUGH = [
    (
        "latest-at-range",
        "fleet_points",
        {"contents": EVERYTHING, "range": time_range("frame", 104, fill_mode=cloud_pb2.FILL_MODE_LATEST_AT)},
        {"points": {"start": 104}},
    ),
    (
        "latest-at-range-out-of-order",
        "fleet_scalars",
        {"contents": EVERYTHING, "range": time_range("step", 4, 8, fill_mode=cloud_pb2.FILL_MODE_LATEST_AT)},
        {"scalars": {"index": "step", "start": 4, "end": 8}},
    ),
    (
        "latest-at-range-two-chunkings",
        "fleet-latest-at",
        {"contents": EVERYTHING, "range": time_range("frame", 35, 65, fill_mode=cloud_pb2.FILL_MODE_LATEST_AT)},
        {"per_call": {"start": 35, "end": 65}, "batched": {"start": 35, "end": 65}},
    ),
    (
        "latest-at-after-the-end",
        "fleet-latest-at",
        {"contents": EVERYTHING, "range": time_range("frame", 200, fill_mode=cloud_pb2.FILL_MODE_LATEST_AT)},
        {"per_call": {"times": [200]}, "batched": {"times": [200]}},
    ),
    (
        "latest-at-samples",
        "fleet-latest-at",
        {
            "contents": EVERYTHING,
            "samples": _samples(RECORDING_IDS["per_call"], [15, 55, 95], cloud_pb2.FILL_MODE_LATEST_AT),
        },
        {"per_call": {"times": [15, 55, 95]}},
    ),
    (
        "latest-at-many-samples",
        "fleet-latest-at",
        {
            "contents": EVERYTHING,
            "samples": _samples(RECORDING_IDS["batched"], list(range(5, 130, 3)), cloud_pb2.FILL_MODE_LATEST_AT),
        },
        {"batched": {"times": list(range(5, 130, 3))}},
    ),
    (
        "one-component",
        "fleet-latest-at",
        {
            "contents": entities("/robot", components=["Points3D:colors"]),
            "samples": _samples(RECORDING_IDS["per_call"], [10, 30, 90], cloud_pb2.FILL_MODE_LATEST_AT),
        },
        {"per_call": {"times": [10, 30, 90], "columns": ["/robot:Points3D:colors"]}},
    ),
]


@pytest.mark.parametrize(("label", "dataset", "fields", "checks"), ENOUGH, ids=[c[0] for c in ENOUGH])
def test_latest_at_and_component_candidates_are_enough_for_rerun_s_reader(
    servers: Servers, tmp_path: Path, label: str, dataset: str, fields: dict[str, Any], checks: dict[str, Any]
):
    request = cloud_pb2.FindChunksRequest(**fields)
    reference, ours = (table(r) for r in servers.both("FindChunks", dataset, request))
    mine = set(ours["chunk_id"].to_pylist())
    for name, reading in checks.items():
        whole = reader_rows(servers.files[name], **reading)
        subset = keep_chunks(servers.files[name], mine, tmp_path / f"{name}-candidates.rrd")
        assert reader_rows(subset, **reading) == whole, f"{label}: our candidates miss rows of {name}"
    # and every reference chunk we leave out is one the rows above did without
    assert len(mine) <= len(set(reference["chunk_id"].to_pylist()) | mine)


# --- errors -------------------------------------------------------------------------------------


def _code(client: Redap, rpc: str, request: Any, entry: str) -> tuple[grpc.StatusCode, str]:
    """The status of a call (OK when it answers)."""
    try:
        client.call(rpc, request, entry=entry)
    except grpc.RpcError as exc:
        return exc.code(), exc.details() or ""  # type: ignore[attr-defined]
    return grpc.StatusCode.OK, ""


INVALID_FIND = [
    ("no-mode", {"contents": EVERYTHING}),
    ("no-contents", {"range": time_range("frame")}),
    ("no-segments", {"contents": EVERYTHING, "range": cloud_pb2.RangeSelection(timeline="frame")}),
    (
        "fill-without-start",
        {"contents": EVERYTHING, "range": time_range("frame", fill_mode=cloud_pb2.FILL_MODE_LATEST_AT)},
    ),
    ("end-before-start", {"contents": EVERYTHING, "range": time_range("frame", 5, 1)}),
    ("entity-twice", {"contents": entities("/world/points", "/world/points"), "range": time_range("frame")}),
    ("empty-component", {"contents": entities("/world/points", components=[""]), "range": time_range("frame")}),
    ("unknown-timeline", {"contents": EVERYTHING, "range": time_range("nope")}),
    ("unknown-sample-timeline", {"contents": EVERYTHING, "samples": cloud_pb2.SegmentSamplesSelection(timeline="zzz")}),
]


@pytest.mark.parametrize(("label", "fields"), INVALID_FIND, ids=[c[0] for c in INVALID_FIND])
def test_find_chunks_refuses_what_the_reference_refuses(servers: Servers, label: str, fields: dict[str, Any]):
    request = cloud_pb2.FindChunksRequest(**fields)
    theirs = _code(servers.reference, "FindChunks", request, servers.reference_ids["fleet_points"])
    mine = _code(servers.ours, "FindChunks", request, servers.our_ids["fleet_points"])
    assert theirs[0] == mine[0] == grpc.StatusCode.INVALID_ARGUMENT, (theirs, mine)


def test_an_unknown_timeline_is_named_with_the_dataset_s(servers: Servers):
    request = cloud_pb2.FindChunksRequest(contents=EVERYTHING, range=time_range("nope"))
    code, details = _code(servers.ours, "FindChunks", request, servers.our_ids["fleet_points"])
    assert code == grpc.StatusCode.INVALID_ARGUMENT
    assert "'nope'" in details and "frame, log_time, sim" in details


def test_earliest_at_fill_is_unimplemented_as_by_the_reference(servers: Servers):
    request = cloud_pb2.FindChunksRequest(
        contents=EVERYTHING, range=time_range("frame", 1, fill_mode=cloud_pb2.FILL_MODE_EARLIEST_AT)
    )
    for client, ids in ((servers.reference, servers.reference_ids), (servers.ours, servers.our_ids)):
        assert _code(client, "FindChunks", request, ids["fleet_points"])[0] == grpc.StatusCode.UNIMPLEMENTED


def test_an_unknown_dataset_is_not_found(servers: Servers):
    unknown = str(Tuid(0x18EA87A1F8500123, 1))
    for rpc, request in (
        ("GetDatasetSchema", cloud_pb2.GetDatasetSchemaRequest()),
        ("FindChunks", cloud_pb2.FindChunksRequest(contents=EVERYTHING, range=time_range("frame"))),
        ("QueryDataset", cloud_pb2.QueryDatasetRequest(select_all_entity_paths=True)),
    ):
        for client in (servers.reference, servers.ours):
            code, details = _code(client, rpc, request, unknown)
            assert code == grpc.StatusCode.NOT_FOUND, (rpc, client.port, details)
        assert "FindEntries" in _code(servers.ours, rpc, request, unknown)[1]


def _index(timeline: str) -> common_pb2.IndexColumnSelector:
    return common_pb2.IndexColumnSelector(timeline=common_pb2.Timeline(name=timeline))


INVALID_QUERY = [
    ("entities-and-all", {"select_all_entity_paths": True, "entity_paths": [common_pb2.EntityPath(path="/a")]}),
    ("chunk-ids", {"select_all_entity_paths": True, "chunk_ids": [common_pb2.Tuid(time_ns=1, inc=2)]}),
    ("exclude-static", {"select_all_entity_paths": True, "exclude_static_data": True}),
    ("limit", {"select_all_entity_paths": True, "scan_parameters": common_pb2.ScanParameters(limit_len=3)}),
    ("latest-at-without-time", {"query": cloud_pb2.Query(latest_at=cloud_pb2.QueryLatestAt(index=_index("frame")))}),
    ("range-without-bounds", {"query": cloud_pb2.Query(range=cloud_pb2.QueryRange(index=_index("frame")))}),
    (
        "latest-at-off-the-range-start",
        {
            "query": cloud_pb2.Query(
                latest_at=cloud_pb2.QueryLatestAt(index=_index("frame"), at=101),
                range=cloud_pb2.QueryRange(index=_index("frame"), index_range=common_pb2.TimeRange(start=102, end=103)),
            )
        },
    ),
    (
        "per-segment-values-without-segments",
        {
            "query": cloud_pb2.Query(
                latest_at=cloud_pb2.QueryLatestAt(
                    index=_index("frame"), per_segment_values=[cloud_pb2.IndexValueList(values=[1])]
                )
            )
        },
    ),
    (
        "unknown-timeline",
        {
            "query": cloud_pb2.Query(
                range=cloud_pb2.QueryRange(index=_index("zz"), index_range=common_pb2.TimeRange(start=1, end=2))
            )
        },
    ),
]


@pytest.mark.parametrize(("label", "fields"), INVALID_QUERY, ids=[c[0] for c in INVALID_QUERY])
def test_query_dataset_refuses_what_the_reference_refuses(servers: Servers, label: str, fields: dict[str, Any]):
    request = cloud_pb2.QueryDatasetRequest(**fields)
    theirs = _code(servers.reference, "QueryDataset", request, servers.reference_ids["fleet_points"])
    mine = _code(servers.ours, "QueryDataset", request, servers.our_ids["fleet_points"])
    assert theirs[0] == mine[0] == grpc.StatusCode.INVALID_ARGUMENT, (theirs, mine)


QUERIES = [
    ("nothing-named", {}),
    ("everything", {"select_all_entity_paths": True}),
    ("one-entity", {"entity_paths": [common_pb2.EntityPath(path="/world/sparse")]}),
    ("one-segment", {"select_all_entity_paths": True, "segment_ids": [common_pb2.SegmentId(id="rec-points")]}),
    ("unknown-segment", {"select_all_entity_paths": True, "segment_ids": [common_pb2.SegmentId(id="nope")]}),
    ("static-only", {"select_all_entity_paths": True, "query": cloud_pb2.Query(latest_at=cloud_pb2.QueryLatestAt())}),
    (
        "range",
        {
            "select_all_entity_paths": True,
            "query": cloud_pb2.Query(
                range=cloud_pb2.QueryRange(index=_index("frame"), index_range=common_pb2.TimeRange(start=102, end=103))
            ),
        },
    ),
    (
        "range-filled",
        {
            "select_all_entity_paths": True,
            "query": cloud_pb2.Query(
                latest_at=cloud_pb2.QueryLatestAt(index=_index("frame"), at=102),
                range=cloud_pb2.QueryRange(index=_index("frame"), index_range=common_pb2.TimeRange(start=102, end=103)),
            ),
        },
    ),
    (
        "per-segment-values",
        {
            "select_all_entity_paths": True,
            "segment_ids": [common_pb2.SegmentId(id="rec-points")],
            "query": cloud_pb2.Query(
                latest_at=cloud_pb2.QueryLatestAt(
                    index=_index("frame"), per_segment_values=[cloud_pb2.IndexValueList(values=[102])]
                )
            ),
        },
    ),
]


@pytest.mark.parametrize(("label", "fields"), QUERIES, ids=[c[0] for c in QUERIES])
def test_query_dataset_candidates_cover_the_reference_s(servers: Servers, label: str, fields: dict[str, Any]):
    request = cloud_pb2.QueryDatasetRequest(**fields)
    reference, ours = (table(r) for r in servers.both("QueryDataset", "fleet_points", request))
    assert ours.schema.equals(reference.schema, check_metadata=True)
    assert set(reference["chunk_id"].to_pylist()) <= set(ours["chunk_id"].to_pylist())


# --- runs that are not sealed, or not readable --------------------------------------------------


@pytest.fixture
def node(tmp_path: Path) -> Iterator[DepotNode]:
    made = build_node(tmp_path / "node")
    yield made
    made.close()


def test_a_hot_run_answers_what_it_answers_once_sealed(node: DepotNode, recordings: dict[str, Path]):
    node.upload(recordings["points"])
    with session_scope(node.catalog) as session:
        entry = {d.name: d.entry_id for d in queries.datasets(session)}["fleet_points"]
    request = cloud_pb2.FindChunksRequest(
        contents=EVERYTHING, range=time_range("frame", 102, fill_mode=cloud_pb2.FILL_MODE_LATEST_AT)
    )
    answers = []
    for _ in ("hot", "sealed"):
        server = CatalogServerThread(node.depot).start()
        client = Redap(server.port)
        try:
            found = table(client.call("FindChunks", request, entry=entry))
            schema = _schema(client.call("GetDatasetSchema", cloud_pb2.GetDatasetSchemaRequest(), entry=entry))
            answers.append((_rows(found), schema))
        finally:
            client.close()
            server.stop()
        node.seal_all()
    (hot_rows, hot_schema), (sealed_rows, sealed_schema) = answers
    assert hot_rows == sealed_rows and len(hot_rows) == 7  # the same chunks, sizes and times
    assert hot_schema.equals(sealed_schema, check_metadata=True)


def test_a_cold_run_fails_a_query_naming_it_and_is_left_out_of_one_over_every_run(
    node: DepotNode, recordings: dict[str, Path]
):
    node.upload(recordings["merge_a"])
    node.seal_all()
    node.clock.advance(days=31)  # past the warm days of the default policy: merge-a goes cold
    outcomes = run_plan(node.retention, plan(node.retention, [ARCHIVE]))
    assert [(o.action.run_id, o.ok) for o in outcomes] == [("rec-merge-a", True)]
    node.upload(recordings["merge_b"])
    node.seal_all()
    with session_scope(node.catalog) as session:
        entry = {d.name: d.entry_id for d in queries.datasets(session)}["fleet_merge"]
    server = CatalogServerThread(node.depot).start()
    client = Redap(server.port)
    try:
        named = cloud_pb2.FindChunksRequest(
            contents=EVERYTHING, range=time_range("frame", segments=segments("rec-merge-a"))
        )
        code, details = _code(client, "FindChunks", named, entry)
        assert code == grpc.StatusCode.FAILED_PRECONDITION
        assert "rec-merge-a" in details and "fleet runs restore rec-merge-a" in details
        every = cloud_pb2.FindChunksRequest(contents=EVERYTHING, range=time_range("frame"))
        assert set(table(client.call("FindChunks", every, entry=entry))["chunk_segment_id"].to_pylist()) == {
            "rec-merge-b"
        }
        schema = _schema(client.call("GetDatasetSchema", cloud_pb2.GetDatasetSchemaRequest(), entry=entry))
        assert "tick" in schema.names and "frame" not in schema.names  # merge-b's columns alone
    finally:
        client.close()
        server.stop()


def test_candidates_stream_in_parts_of_bounded_size(servers: Servers, monkeypatch: pytest.MonkeyPatch):
    request = cloud_pb2.FindChunksRequest(contents=EVERYTHING, range=time_range("frame"))
    whole = servers.ours.call("FindChunks", request, entry=servers.our_ids["fleet-latest-at"])
    monkeypatch.setattr(candidate_table, "PART_ROWS", 5)
    parts = servers.ours.call("FindChunks", request, entry=servers.our_ids["fleet-latest-at"])
    sizes = [read_dataframe_part(p.data).num_rows for p in parts]
    assert len(whole) == 2 and max(sizes) == 5 and len(sizes) > 2  # a part a run at most; now five rows a part
    assert table(parts).equals(table(whole))
