"""A dataset's segment table (services/redap/segments.py): its columns from catalog rows alone,
projection, segment filters and bounded parts, on DuckDB and Postgres; its schema, field metadata
and values compared with Rerun's own `rerun server` serving the same files; and the real SDK's
`segment_table()` showing the fleet's columns."""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterator
from typing import Any

import grpc
import pyarrow as pa
import pytest

from catalog.queries import EntityRecord
from core.errors import InvalidArgumentError, NotFoundError
from services.auth.scopes import Principal, Scope
from services.redap import segments
from services.redap.dataframe import read_dataframe_part
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from tests.services.ingest.live_server import LiveServer
from tests.services.redap.client import Redap
from tests.services.redap.depots import (
    NOW,
    catalog_depot,
    dataset_ids,
    entry_of,
    record,
    save,
    status_of,
)

K = cloud_pb2
READER = Principal("alice", frozenset({Scope.READ}), token_id="t1")
FIXED = [
    pa.field("rerun_segment_id", pa.utf8(), nullable=False),
    pa.field("rerun_layer_names", pa.list_(pa.field("item", pa.utf8(), nullable=False)), nullable=False),
    pa.field("rerun_storage_urls", pa.list_(pa.field("item", pa.utf8(), nullable=False)), nullable=False),
    pa.field("rerun_last_updated_at", pa.timestamp("ns"), nullable=False),
    pa.field("rerun_num_chunks", pa.uint64(), nullable=False),
    pa.field("rerun_size_bytes", pa.uint64(), nullable=False),
]
DEPOT_COLUMNS = {
    "property:depot:robot_id": pa.utf8(),
    "property:depot:tier": pa.utf8(),
    "property:depot:status": pa.utf8(),
    "property:depot:started_at": pa.timestamp("ns"),
    "property:depot:ended_at": pa.timestamp("ns"),
    "property:depot:pinned": pa.bool_(),
}
TAGS_COLUMN = "property:depot:tags"  # the corpus's: always there (metric columns come with metrics)


def ns(moment: dt.datetime) -> int:
    return int(moment.timestamp()) * 10**9 + moment.microsecond * 1000


def schema_of(depot: Depot, entry: Tuid) -> pa.Schema:
    answer = segments.table_schema(depot, READER, entry)
    return pa.ipc.read_schema(pa.py_buffer(answer.schema.arrow_schema))


def scan_parts(depot: Depot, entry: Tuid, **request: Any) -> list[pa.Table]:
    answers = segments.scan(depot, READER, entry, K.ScanSegmentTableRequest(**request))
    return [read_dataframe_part(a.data) for a in answers]


def scan(depot: Depot, entry: Tuid, **request: Any) -> pa.Table:
    return pa.concat_tables(scan_parts(depot, entry, **request))


def rows(table: pa.Table) -> dict[str, dict[str, Any]]:
    """segment id -> row, times as integers (nanoseconds)."""
    plain = pa.schema(
        [
            f.with_type(pa.int64())
            if pa.types.is_timestamp(f.type) or pa.types.is_duration(f.type)
            else f.with_type(pa.list_(pa.int64()))
            if pa.types.is_list(f.type) and pa.types.is_timestamp(f.type.value_type)
            else f
            for f in table.schema
        ]
    )
    return {r["rerun_segment_id"]: r for r in table.cast(plain).to_pylist()}


@pytest.fixture
def depot(fresh_catalog_url: str) -> Iterator[Depot]:
    with catalog_depot(fresh_catalog_url) as made:
        yield made


# --- the columns -----------------------------------------------------------------------------


def test_rerun_columns_come_first_as_rerun_types_them(depot: Depot):
    save(depot, record("run-1"))
    schema = schema_of(depot, entry_of(depot, "nav"))
    assert list(schema)[: len(FIXED)] == FIXED
    assert all(not f.metadata for f in FIXED)
    assert schema.metadata is None


def test_recording_properties_are_columns_named_and_marked_as_rerun_does(depot: Depot):
    properties = {
        "recording": {"RecordingInfo:start_time": 1_700_000_000 * 10**9, "RecordingInfo:name": "bench run"},
        "fleet": {"robot_id": "robot-7"},
        "location": {"GeoPoints:positions": [46.5, 6.5]},
    }
    entities = [
        *record("x").entities,
        segments_entity("/__properties/location", ["rerun.archetypes.GeoPoints"], ["GeoPoints:positions"]),
    ]
    save(depot, record("run-1", properties=properties, entities=entities))
    fields = {f.name: f for f in schema_of(depot, entry_of(depot, "nav"))}
    assert fields["property:RecordingInfo:start_time"] == pa.field(
        "property:RecordingInfo:start_time",
        pa.list_(pa.int64()),
        metadata={
            "rerun:archetype": "rerun.archetypes.RecordingInfo",
            "rerun:component": "RecordingInfo:start_time",
            "rerun:component_type": "rerun.components.Timestamp",
            "rerun:entity_path": "/__properties",
            "rerun:kind": "data",
        },
    )
    assert fields["property:RecordingInfo:name"].metadata[b"rerun:component_type"] == b"rerun.components.Name"
    assert fields["property:fleet:robot_id"] == pa.field(
        "property:fleet:robot_id",
        pa.list_(pa.utf8()),
        metadata={"rerun:component": "robot_id", "rerun:entity_path": "/__properties/fleet", "rerun:kind": "data"},
    )
    location = fields["property:location:GeoPoints:positions"]
    assert location.metadata[b"rerun:archetype"] == b"rerun.archetypes.GeoPoints"
    assert location.metadata[b"rerun:entity_path"] == b"/__properties/location"
    assert all(f.nullable for name, f in fields.items() if name.startswith("property:"))


def segments_entity(path: str, archetypes: list[str], components: list[str]) -> EntityRecord:
    return EntityRecord(path, 1, 1, 1, 10, archetypes, components)


def test_property_values_take_the_type_their_runs_hold(depot: Depot):
    first = {"s": "text", "i": 1, "f": 1.5, "b": True, "mixed": 1, "int_float": 1, "nan": "NaN", "l": [1, 2, 3]}
    second = {
        "s": "more",
        "i": 2,
        "f": 2.5,
        "b": False,
        "mixed": "one",
        "int_float": 2.5,
        "nan": 1.5,
        "nested": {"a": 1},
    }
    save(depot, record("run-1", properties={"info": first}), record("run-2", properties={"info": second}))
    table = scan(depot, entry_of(depot, "nav"))
    types = {f.name.removeprefix("property:info:"): f.type.value_type for f in table.schema if "info:" in f.name}
    assert types == {
        "s": pa.utf8(),
        "i": pa.int64(),
        "f": pa.float64(),
        "b": pa.bool_(),
        "mixed": pa.utf8(),  # runs disagree: shown as text
        "int_float": pa.float64(),
        "nan": pa.float64(),  # NaN is kept in the catalog as the text "NaN"
        "l": pa.int64(),
        "nested": pa.utf8(),  # a struct: JSON text
    }
    got = {n: r for n, r in rows(table).items()}
    one, two = got["run-1"], got["run-2"]
    assert (one["property:info:s"], two["property:info:s"]) == (["text"], ["more"])
    assert (one["property:info:mixed"], two["property:info:mixed"]) == (["1"], ["one"])
    assert (one["property:info:int_float"], two["property:info:int_float"]) == ([1.0], [2.5])
    assert math.isnan(one["property:info:nan"][0]) and two["property:info:nan"] == [1.5]
    assert one["property:info:l"] == [1, 2, 3] and two["property:info:l"] is None  # a run without it: null
    assert (one["property:info:nested"], two["property:info:nested"]) == (None, ['{"a": 1}'])


def test_the_depots_own_columns_say_what_the_catalog_knows(depot: Depot):
    started = NOW - dt.timedelta(hours=1)
    save(
        depot,
        record("run-1", robot_id="robot-9", started_at=started, ended_at=None, status="live"),
        record("run-2"),
        later={"run-2": {"tier": "cold", "pinned": True}},
    )
    table = scan(depot, entry_of(depot, "nav"))
    assert {n: table.schema.field(n).type.value_type for n in DEPOT_COLUMNS} == DEPOT_COLUMNS
    assert table.schema.field("property:depot:tier").metadata == {
        b"rerun:component": b"tier",
        b"rerun:entity_path": b"/__properties/depot",
        b"rerun:kind": b"data",
    }
    got = rows(table)
    assert {c: got["run-1"][c] for c in DEPOT_COLUMNS} == {
        "property:depot:robot_id": ["robot-9"],
        "property:depot:tier": ["hot"],
        "property:depot:status": ["live"],
        "property:depot:started_at": [ns(started)],
        "property:depot:ended_at": None,
        "property:depot:pinned": [False],
    }
    assert (got["run-2"]["property:depot:tier"], got["run-2"]["property:depot:pinned"]) == (["cold"], [True])


def test_a_recording_property_named_depot_yields_to_the_depots_columns(depot: Depot):
    save(depot, record("run-1", properties={"depot": {"tier": "mine", "site": "lab"}}))
    got = rows(scan(depot, entry_of(depot, "nav")))["run-1"]
    assert got["property:depot:tier"] == ["hot"]
    assert "property:depot:site" not in got


def test_timelines_are_start_and_end_columns_of_their_type(depot: Depot):
    from catalog.queries import TimelineRecord

    save(
        depot,
        record(
            "run-1",
            timelines=[TimelineRecord("frame", "sequence", 3, 9), TimelineRecord("log_time", "timestamp", 5, 6)],
        ),
        record(
            "run-2", timelines=[TimelineRecord("sim", "duration", 0, 10), TimelineRecord("frame", "duration", 1, 2)]
        ),
        record("run-3", timelines=[TimelineRecord("frame", "sequence", 0, 1)]),
    )
    table = scan(depot, entry_of(depot, "nav"))
    timelines = [f for f in table.schema if not f.name.startswith(("rerun_", "property:"))]
    assert [f.name for f in timelines] == [
        "frame:end",
        "frame:start",
        "log_time:end",
        "log_time:start",
        "sim:end",
        "sim:start",
    ]
    types = {f.name: f.type for f in timelines}
    assert (types["frame:start"], types["log_time:end"], types["sim:start"]) == (
        pa.int64(),  # most runs log frame as a sequence
        pa.timestamp("ns"),
        pa.duration("ns"),
    )
    assert table.schema.field("sim:start").metadata == {
        b"rerun:index": b"sim",
        b"rerun:index_kind": b"duration",
        b"rerun:index_marker": b"start",
        b"rerun:kind": b"index",
    }
    got = rows(table)
    assert (got["run-1"]["frame:start"], got["run-1"]["frame:end"]) == (3, 9)
    assert got["run-2"]["frame:start"] is None  # its frame is a duration: not this column's type
    assert (got["run-2"]["sim:start"], got["run-2"]["sim:end"], got["run-1"]["sim:start"]) == (0, 10, None)


def test_rows_hold_rerun_s_columns_from_the_catalog(depot: Depot):
    save(depot, record("run-1", chunks=7, bytes=12345))
    got = rows(scan(depot, entry_of(depot, "nav")))["run-1"]
    assert got["rerun_layer_names"] == ["base"]
    assert got["rerun_storage_urls"] == ["fleet:///v1/runs/run-1/recording.rrd"]
    assert (got["rerun_num_chunks"], got["rerun_size_bytes"], got["rerun_last_updated_at"]) == (7, 12345, ns(NOW))


# --- which rows ------------------------------------------------------------------------------


def test_segments_are_the_datasets_runs_in_every_tier_but_deleted(depot: Depot):
    save(
        depot,
        *(record(f"run-{t}") for t in ("hot", "warm", "cold", "deleted")),
        record("arm-1", "arm"),
        later={"run-warm": {"tier": "warm"}, "run-cold": {"tier": "cold"}, "run-deleted": {"tier": "deleted"}},
    )
    got = rows(scan(depot, entry_of(depot, "nav")))
    assert {n: r["property:depot:tier"] for n, r in got.items()} == {
        "run-cold": ["cold"],
        "run-hot": ["hot"],
        "run-warm": ["warm"],
    }


@pytest.mark.parametrize(
    ("segment_filter", "found"),
    [
        (K.SegmentIdFilter(scan_only=K.SegmentIdList(segment_ids=["run-2", "arm-1", "nope", "run-2"])), ["run-2"]),
        (K.SegmentIdFilter(scan_only=K.SegmentIdList()), []),  # an empty list scans nothing
        (K.SegmentIdFilter(skip=K.SegmentIdList(segment_ids=["run-1", "nope"])), ["run-2", "run-3"]),
        (K.SegmentIdFilter(skip=K.SegmentIdList()), ["run-1", "run-2", "run-3"]),  # skips nothing
        (K.SegmentIdFilter(), ["run-1", "run-2", "run-3"]),
    ],
)
def test_segment_id_filters(depot: Depot, segment_filter: Any, found: list[str]):
    save(depot, record("run-1"), record("run-2"), record("run-3"), record("arm-1", "arm"))
    table = scan(depot, entry_of(depot, "nav"), segment_id_filter=segment_filter)
    assert table.column("rerun_segment_id").to_pylist() == found
    assert table.schema == schema_of(depot, entry_of(depot, "nav"))  # no rows: the columns still


def test_projection_gives_the_columns_asked_for_in_that_order(depot: Depot):
    save(depot, record("run-1"), record("run-2"))
    asked = ["property:fleet:robot_id", "rerun_num_chunks", "frame:end", "rerun_segment_id"]
    table = scan(depot, entry_of(depot, "nav"), columns=asked)
    assert table.column_names == asked
    assert table.column("property:fleet:robot_id").to_pylist() == [["robot-7"], ["robot-7"]]
    cheap = scan(depot, entry_of(depot, "nav"), columns=["rerun_last_updated_at"])  # what the viewer asks second
    assert cheap.column_names == ["rerun_last_updated_at"] and cheap.num_rows == 2


@pytest.mark.parametrize(
    ("columns", "message"),
    [
        (["rerun_segment_id", "nope"], "the segment table has no column 'nope': GetSegmentTableSchema lists"),
        (["rerun_segment_id", "rerun_segment_id"], "column 'rerun_segment_id' is asked for twice"),
        (["property:fleet:nope"], "no column 'property:fleet:nope'"),
    ],
)
def test_an_unknown_or_repeated_column_is_invalid(depot: Depot, columns: list[str], message: str):
    save(depot, record("run-1"))
    with pytest.raises(InvalidArgumentError, match=message):
        scan(depot, entry_of(depot, "nav"), columns=columns)


def test_a_large_dataset_comes_in_bounded_parts(depot: Depot, monkeypatch: pytest.MonkeyPatch):
    save(depot, *(record(f"run-{i:02}", properties={"notes": {"text": "x" * 2000}}) for i in range(12)))
    whole = scan(depot, entry_of(depot, "nav"))
    monkeypatch.setattr(segments, "FIRST_PAGE_ROWS", 2)  # the first page, read before the first part goes
    monkeypatch.setattr(segments, "PAGE_ROWS", 5)  # runs read from the catalog at a time after it
    monkeypatch.setattr(segments, "PART_BYTES", 5000)  # about two runs' notes
    parts = scan_parts(depot, entry_of(depot, "nav"))
    assert len(parts) >= 6 and max(p.num_rows for p in parts) <= 3
    assert all(p.nbytes < 3 * 5000 for p in parts)
    assert pa.concat_tables(parts).equals(whole)
    skipped = scan(
        depot, entry_of(depot, "nav"), segment_id_filter=K.SegmentIdFilter(skip=K.SegmentIdList(segment_ids=["run-03"]))
    )
    assert skipped.num_rows == 11 and "run-03" not in skipped.column("rerun_segment_id").to_pylist()


def test_a_dataset_whose_runs_are_all_deleted_is_one_empty_part(depot: Depot):
    save(depot, record("run-1"), later={"run-1": {"tier": "deleted"}})
    (part,) = scan_parts(depot, entry_of(depot, "nav"))
    assert part.num_rows == 0
    assert [f.name for f in part.schema] == [f.name for f in FIXED] + sorted([*DEPOT_COLUMNS, TAGS_COLUMN])


def test_an_unknown_dataset_is_not_found(depot: Depot):
    with pytest.raises(NotFoundError, match="no dataset has entry id"):
        segments.table_schema(depot, READER, Tuid(1, 2))
    with pytest.raises(NotFoundError, match="no dataset has entry id"):
        scan(depot, Tuid(1, 2))


# --- compared with Rerun's own server; Rerun's SDK -------------------------------------------

# Columns only one side has, by design: the depot's facts, and a secret the depot never stores.
OURS_ONLY = {*DEPOT_COLUMNS, TAGS_COLUMN}
REFERENCE_ONLY = {"property:fleet:token"}
# Values that differ by design: where the file is, when it was registered, its size as stored.
OWN_VALUES = {"rerun_storage_urls", "rerun_last_updated_at", "rerun_size_bytes"}


def remote_schema(client: Redap, entry: str) -> pa.Schema:
    answer = client.call("GetSegmentTableSchema", K.GetSegmentTableSchemaRequest(), entry=entry)
    return pa.ipc.read_schema(pa.py_buffer(answer.schema.arrow_schema))


def remote_scan(client: Redap, entry: str, **request: Any) -> pa.Table:
    parts = client.call("ScanSegmentTable", K.ScanSegmentTableRequest(**request), entry=entry)
    return pa.concat_tables([read_dataframe_part(p.data) for p in parts])


def fields(schema: pa.Schema, leave_out: set[str]) -> dict[str, pa.Field]:
    return {f.name: f for f in schema if f.name not in leave_out}


@pytest.mark.sdk
def test_segment_tables_match_rerun_servers_for_the_same_files(served_client: Redap, scenes_reference: Redap):
    ours, reference = served_client, scenes_reference
    ids = {"reference": dataset_ids(reference), "ours": dataset_ids(ours)}
    for name in ("fleet_points", "fleet_props", "fleet_merge"):
        theirs_schema = remote_schema(reference, ids["reference"][name])
        our_schema = remote_schema(ours, ids["ours"][name])
        assert list(our_schema)[: len(FIXED)] == list(theirs_schema)[: len(FIXED)] == FIXED
        theirs, mine = fields(theirs_schema, REFERENCE_ONLY), fields(our_schema, OURS_ONLY)
        assert mine.keys() == theirs.keys(), name
        for column, field in theirs.items():  # type, nullability and every rerun:* metadata entry
            assert mine[column].equals(field, check_metadata=True), (name, mine[column], field)
        assert set(our_schema.names) >= OURS_ONLY

        their_rows = rows(remote_scan(reference, ids["reference"][name]))
        our_rows = rows(remote_scan(ours, ids["ours"][name]))
        assert our_rows.keys() == their_rows.keys(), name
        for segment, row in their_rows.items():
            same = set(theirs) - OWN_VALUES
            assert {c: our_rows[segment][c] for c in same} == {c: row[c] for c in same}, (name, segment)


@pytest.mark.sdk
def test_projection_and_filters_answer_as_rerun_servers_do(served_client: Redap, scenes_reference: Redap):
    ours, reference = served_client, scenes_reference
    for client in (reference, ours):
        entry = dataset_ids(client)["fleet_merge"]
        asked = ["rerun_num_chunks", "tick:end", "rerun_segment_id"]
        projected = remote_scan(client, entry, columns=asked)
        assert projected.column_names == asked
        assert sorted(projected.column("rerun_segment_id").to_pylist()) == ["rec-merge-a", "rec-merge-b"]
        only = K.SegmentIdFilter(scan_only=K.SegmentIdList(segment_ids=["rec-merge-b"]))
        kept = remote_scan(client, entry, columns=["rerun_segment_id"], segment_id_filter=only)
        assert kept.column("rerun_segment_id").to_pylist() == ["rec-merge-b"]
        skip = K.SegmentIdFilter(skip=K.SegmentIdList(segment_ids=["rec-merge-b"]))
        assert remote_scan(client, entry, segment_id_filter=skip).column("rerun_segment_id").to_pylist() == [
            "rec-merge-a"
        ]
        none = K.SegmentIdFilter(scan_only=K.SegmentIdList())
        assert remote_scan(client, entry, columns=["rerun_segment_id"], segment_id_filter=none).num_rows == 0
        for columns in (["rerun_segment_id", "nope"], ["rerun_segment_id", "rerun_segment_id"]):
            request = K.ScanSegmentTableRequest(columns=columns)
            assert status_of(client, "ScanSegmentTable", request, entry) == grpc.StatusCode.INVALID_ARGUMENT


@pytest.mark.sdk
def test_the_sdk_shows_the_fleets_columns_in_the_segment_table(served: LiveServer):
    import rerun as rr

    client = rr.catalog.CatalogClient(f"rerun+http://127.0.0.1:{served.grpc_port}")
    assert sorted(client.get_dataset("fleet_merge").segment_ids()) == ["rec-merge-a", "rec-merge-b"]
    table = client.get_dataset("fleet_props").segment_table().to_arrow_table()
    (row,) = table.select(["rerun_segment_id", "property:depot:robot_id", "property:depot:tier"]).to_pylist()
    assert row == {
        "rerun_segment_id": "rec-properties",
        "property:depot:robot_id": ["robot-7"],  # from its fleet property
        "property:depot:tier": ["hot"],
    }
    assert table.column("property:vehicle:model").to_pylist() == [["crawler"]]
    assert "property:fleet:token" not in table.column_names  # a secret is never stored, nor shown
    warm = client.get_dataset("fleet_points").segment_table().to_arrow_table()
    assert warm.column("property:depot:tier").to_pylist() == [["warm"]]
    assert warm.column("property:depot:status").to_pylist() == [["closed"]]
