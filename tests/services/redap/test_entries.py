"""The catalog (services/redap/entries.py): Version, WhoAmI, FindEntries with Rerun's filter rules,
ReadDatasetEntry and the `__entries` system table, over DuckDB and Postgres catalogs; the same
answers compared with Rerun's own `rerun server` serving the same files; and the real SDK's
`CatalogClient` against `fleet serve`, with auth on."""

from __future__ import annotations

import datetime as dt
import os
import re
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass

import grpc
import pyarrow as pa
import pytest

import services
from core.errors import InvalidArgumentError, NotFoundError
from services.auth.scopes import Principal, Scope, local_principal
from services.redap import entries
from services.redap.dataframe import read_dataframe_part
from services.redap.depot import Depot
from services.redap.entries import ENTRIES_SCHEMA, ENTRIES_TABLE_ID
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid
from services.rrd.pb import common_pb2
from tests.services.ingest.live_server import FLEET, LiveServer
from tests.services.redap.client import Redap
from tests.services.redap.depots import (
    NOW,
    catalog_depot,
    dataset_ids,
    entry_of,
    record,
    rerun_own,
    save,
    serving,
    status_of,
    table_ids,
)
from tests.services.rrd.recordings import Recording

K = cloud_pb2
READER = Principal("alice", frozenset({Scope.READ}), token_id="t1")


@pytest.fixture
def depot(fresh_catalog_url: str) -> Iterator[Depot]:
    """A catalog with two datasets: nav (two runs, the second a minute later) and arm."""
    with catalog_depot(fresh_catalog_url) as made:
        save(made, record("nav-1"), record("arm-1", "arm"))
        save(made, record("nav-2"), now=NOW + dt.timedelta(minutes=1))
        yield made


def find(depot: Depot, **entry_filter: object) -> list[tuple[str, int]]:
    request = K.FindEntriesRequest(filter=K.EntryFilter(**entry_filter))  # type: ignore[arg-type]
    return sorted((e.name, e.entry_kind) for e in entries.find_entries(depot, READER, request).entries)


# What Rerun's viewer asks FindEntries for.
VIEWER_KINDS = [
    K.ENTRY_KIND_DATASET,
    K.ENTRY_KIND_DATASET_VIEW,
    K.ENTRY_KIND_TABLE,
    K.ENTRY_KIND_TABLE_VIEW,
    K.ENTRY_KIND_BLUEPRINT_DATASET,
    K.ENTRY_KIND_ASSET_DATASET,
]
DATASETS = [("arm", K.ENTRY_KIND_DATASET), ("nav", K.ENTRY_KIND_DATASET)]
TABLE = [("__entries", K.ENTRY_KIND_TABLE)]


# --- the server ------------------------------------------------------------------------------


def test_version_names_the_depot_and_its_version():
    answer = entries.version()
    assert answer.version == services.__version__
    assert answer.build_info.crate_name == "fleet-telemetry"
    semver = answer.build_info.version
    assert f"{semver.major}.{semver.minor}.{semver.patch}" == re.match(r"\d+\.\d+\.\d+", services.__version__)[0]  # type: ignore[index]
    assert not answer.features  # no optional request fields consumed, none announced
    assert not answer.HasField("cloud_provider")


@pytest.mark.parametrize(
    ("scopes", "can_read", "can_write"),
    [
        ({Scope.READ}, True, False),
        ({Scope.WRITE}, True, True),
        ({Scope.ADMIN}, True, True),
        ({Scope.INGEST}, False, False),  # a robot's token reads nothing
    ],
)
def test_who_am_i_tells_what_the_token_may_do(scopes: set[Scope], can_read: bool, can_write: bool):
    answer = entries.who_am_i(None, Principal("bob", frozenset(scopes), token_id="t2"))  # type: ignore[arg-type]
    assert (answer.user_id, answer.can_read, answer.can_write) == ("bob", can_read, can_write)
    assert answer.HasField("capabilities")  # always set: unset means "a server too old to say"
    assert list(answer.capabilities.capabilities) == ["dataset:find_chunks"]


def test_who_am_i_with_auth_off_may_do_everything():
    answer = entries.who_am_i(None, local_principal())  # type: ignore[arg-type]
    assert (answer.can_read, answer.can_write) == (True, True)


# --- FindEntries -----------------------------------------------------------------------------


def test_no_filter_finds_the_datasets_and_the_entries_table(depot: Depot):
    assert find(depot) == [*TABLE, *DATASETS]
    answer = entries.find_entries(depot, READER, K.FindEntriesRequest())  # no filter at all
    assert sorted(e.name for e in answer.entries) == ["__entries", "arm", "nav"]


@pytest.mark.parametrize(
    ("entry_filter", "found"),
    [
        ({"entry_kinds": [K.ENTRY_KIND_DATASET]}, DATASETS),
        ({"entry_kinds": [K.ENTRY_KIND_TABLE]}, TABLE),
        (
            {"entry_kinds": [K.ENTRY_KIND_DATASET, K.ENTRY_KIND_TABLE, K.ENTRY_KIND_BLUEPRINT_DATASET]},
            [*TABLE, *DATASETS],
        ),
        ({"entry_kinds": [K.ENTRY_KIND_DATASET_VIEW, K.ENTRY_KIND_TABLE_VIEW, K.ENTRY_KIND_ASSET_DATASET]}, []),
        ({"entry_kind": K.ENTRY_KIND_TABLE}, TABLE),  # the legacy field, for older clients
        ({"entry_kind": K.ENTRY_KIND_TABLE, "entry_kinds": [K.ENTRY_KIND_DATASET]}, DATASETS),  # the new one wins
        ({"name": "nav"}, [("nav", K.ENTRY_KIND_DATASET)]),
        ({"name": "__entries"}, TABLE),
        ({"name": "Nav"}, []),  # exact, case-sensitive
        ({"name": "nav", "entry_kinds": [K.ENTRY_KIND_TABLE]}, []),  # every field set must match
    ],
)
def test_find_entries_honours_each_field_of_the_filter(depot: Depot, entry_filter: dict[str, object], found: object):
    assert find(depot, **entry_filter) == found


def test_find_entries_by_id(depot: Depot):
    nav = entry_of(depot, "nav").entry_id()
    assert find(depot, id=nav) == [("nav", K.ENTRY_KIND_DATASET)]
    assert find(depot, id=ENTRIES_TABLE_ID.entry_id()) == TABLE
    assert find(depot, id=nav, name="arm") == []
    assert find(depot, id=common_pb2.EntryId()) == []  # an id without its TUID matches nothing
    assert find(depot, id=Tuid(1, 2).entry_id()) == []


@pytest.mark.parametrize(
    "entry_filter",
    [{"entry_kinds": [K.ENTRY_KIND_UNSPECIFIED, K.ENTRY_KIND_DATASET]}, {"entry_kind": K.ENTRY_KIND_UNSPECIFIED}],
)
def test_asking_for_the_unspecified_kind_is_invalid(depot: Depot, entry_filter: dict[str, object]):
    with pytest.raises(InvalidArgumentError, match="ENTRY_KIND_UNSPECIFIED"):
        find(depot, **entry_filter)


def test_entries_say_when_they_were_made_and_last_changed(depot: Depot):
    found = {e.name: e for e in entries.find_entries(depot, READER, K.FindEntriesRequest()).entries}
    nav, arm, table = found["nav"], found["arm"], found["__entries"]
    assert (nav.created_at.ToDatetime(dt.UTC), nav.updated_at.ToDatetime(dt.UTC)) == (
        NOW,
        NOW + dt.timedelta(minutes=1),
    )
    assert (arm.created_at.ToDatetime(dt.UTC), arm.updated_at.ToDatetime(dt.UTC)) == (NOW, NOW)
    assert table.created_at.ToDatetime(dt.UTC) == entries.ENTRIES_TABLE_CREATED
    assert table.updated_at.ToDatetime(dt.UTC) == NOW + dt.timedelta(minutes=1)  # when a dataset last changed
    assert Tuid.from_proto(nav.id.id) == entry_of(depot, "nav")


def test_the_entries_table_id_never_changes():
    # Clients keep entry ids in URLs and blueprints: this one is fixed for every depot, for ever.
    assert str(ENTRIES_TABLE_ID) == "18867251EDFA0000b6040bcbf81ba168"


def test_a_catalog_without_datasets_lists_the_entries_table_alone(fresh_catalog_url: str):
    with catalog_depot(fresh_catalog_url) as empty:
        assert find(empty) == TABLE
        (table,) = entries.find_entries(empty, READER, K.FindEntriesRequest()).entries
        assert table.updated_at.ToDatetime(dt.UTC) == entries.ENTRIES_TABLE_CREATED


# --- ReadDatasetEntry ------------------------------------------------------------------------


def test_read_dataset_entry_has_details_a_handle_and_dataset_details(depot: Depot):
    nav = entry_of(depot, "nav")
    dataset = entries.read_dataset_entry(depot, READER, nav).dataset
    assert (dataset.details.name, dataset.details.entry_kind) == ("nav", K.ENTRY_KIND_DATASET)
    assert Tuid.from_proto(dataset.details.id.id) == nav
    assert dataset.HasField("dataset_details")  # present though empty: the viewer refuses an entry without
    assert dataset.dataset_details == K.DatasetDetails()
    handle = dataset.dataset_handle
    assert Tuid.from_proto(handle.entry_id.id) == nav
    assert (handle.dataset_kind, handle.store_kind) == (
        common_pb2.DATASET_KIND_RECORDING,
        common_pb2.STORE_KIND_RECORDING,
    )
    assert handle.dataset_url == "fleet:///v1/runs?application=nav"  # required by the SDK: an absolute URL


def test_dataset_url_is_under_the_public_url(fresh_catalog_url: str):
    with catalog_depot(fresh_catalog_url, public_url="https://fleet.example/") as depot:
        save(depot, record("run-1", "nav/arm 2"))
        answer = entries.read_dataset_entry(depot, READER, entry_of(depot, "nav/arm 2"))
    assert answer.dataset.dataset_handle.dataset_url == "https://fleet.example/v1/runs?application=nav%2Farm%202"


def test_read_dataset_entry_of_no_dataset_is_not_found(depot: Depot):
    with pytest.raises(NotFoundError, match="is the __entries table, not a dataset: read it with ReadTableEntry"):
        entries.read_dataset_entry(depot, READER, ENTRIES_TABLE_ID)
    with pytest.raises(NotFoundError, match="no dataset has entry id"):
        entries.read_dataset_entry(depot, READER, Tuid(1, 2))


# --- the __entries table ---------------------------------------------------------------------


def test_a_table_is_named_by_header_or_for_older_clients_by_body():
    one, other = Tuid(1, 2), Tuid(3, 4)
    assert entries.table_id(one, None) == one
    assert entries.table_id(None, one.entry_id()) == one
    assert entries.table_id(one, one.entry_id()) == one
    assert entries.table_id(one, common_pb2.EntryId()) == one  # a body id without its TUID is none
    with pytest.raises(InvalidArgumentError, match=f"header names entry {one} but the request body names {other}"):
        entries.table_id(one, other.entry_id())
    with pytest.raises(InvalidArgumentError, match="x-rerun-entry-id"):
        entries.table_id(None, None)


def test_read_table_entry_is_the_entries_system_table(depot: Depot):
    table = entries.read_table_entry(depot, READER, ENTRIES_TABLE_ID, K.ReadTableEntryRequest()).table
    assert (table.details.name, table.details.entry_kind) == ("__entries", K.ENTRY_KIND_TABLE)
    assert table.provider_details.type_url == "/rerun.cloud.v1alpha1.SystemTable"
    system = K.SystemTable()
    assert table.provider_details.Unpack(system) and system.kind == K.SYSTEM_TABLE_KIND_ENTRIES
    assert table.HasField("table_details")
    with pytest.raises(NotFoundError, match=r"no table has entry id .*ReadDatasetEntry"):
        entries.read_table_entry(depot, READER, entry_of(depot, "nav"), K.ReadTableEntryRequest())


def test_entries_table_schema_and_rows(depot: Depot):
    schema = entries.table_schema(depot, READER, ENTRIES_TABLE_ID, K.GetTableSchemaRequest()).schema
    assert pa.ipc.read_schema(pa.py_buffer(schema.arrow_schema)).equals(ENTRIES_SCHEMA, check_metadata=True)
    (part,) = entries.scan_table(depot, READER, ENTRIES_TABLE_ID, K.ScanTableRequest())
    table = read_dataframe_part(part.dataframe_part)
    assert table.schema.equals(ENTRIES_SCHEMA, check_metadata=True)
    rows = {r["name"]: r for r in table.cast(_ns_as_int(table.schema)).to_pylist()}
    assert sorted(rows) == ["__entries", "arm", "nav"]
    assert rows["nav"]["id"] == entry_of(depot, "nav").to_bytes()
    assert rows["__entries"]["id"] == ENTRIES_TABLE_ID.to_bytes()
    assert [rows[n]["entry_kind"] for n in ("arm", "nav", "__entries")] == [1, 1, 3]
    assert rows["nav"]["updated_at"] == int((NOW + dt.timedelta(minutes=1)).timestamp()) * 10**9
    with pytest.raises(NotFoundError):
        list(entries.scan_table(depot, READER, entry_of(depot, "nav"), K.ScanTableRequest()))


def test_a_long_entries_table_comes_in_parts(depot: Depot, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setattr(entries, "ENTRIES_PART_ROWS", 2)
    parts = [read_dataframe_part(p.dataframe_part) for p in entries.scan_table(depot, READER, ENTRIES_TABLE_ID, None)]  # type: ignore[arg-type]
    assert [p.num_rows for p in parts] == [2, 1]
    assert sorted(n for p in parts for n in p.column("name").to_pylist()) == ["__entries", "arm", "nav"]


def _ns_as_int(schema: pa.Schema) -> pa.Schema:
    return pa.schema([f.with_type(pa.int64()) if pa.types.is_timestamp(f.type) else f for f in schema])


# --- compared with Rerun's own server, and Rerun's own SDK -----------------------------------


@pytest.mark.sdk
def test_entries_answer_as_rerun_server_does(served_client: Redap, scenes_reference: Redap):
    clients = {"reference": scenes_reference, "ours": served_client}
    viewer_filter = K.EntryFilter(entry_kinds=VIEWER_KINDS)
    listed = {}
    for side, client in clients.items():
        found = client.call("FindEntries", K.FindEntriesRequest(filter=viewer_filter)).entries
        listed[side] = {e.name: e.entry_kind for e in found if not rerun_own(e.name)}
    assert (
        listed["ours"]
        == listed["reference"]
        == {
            "__entries": K.ENTRY_KIND_TABLE,
            "fleet_points": K.ENTRY_KIND_DATASET,
            "fleet_props": K.ENTRY_KIND_DATASET,
            "fleet_merge": K.ENTRY_KIND_DATASET,
        }
    )

    tables = {side: table_ids(client)["__entries"] for side, client in clients.items()}
    read = {s: c.call("ReadTableEntry", K.ReadTableEntryRequest(), entry=tables[s]).table for s, c in clients.items()}
    assert read["ours"].provider_details == read["reference"].provider_details
    assert read["ours"].details.entry_kind == read["reference"].details.entry_kind
    assert read["ours"].HasField("table_details") and read["reference"].HasField("table_details")

    schemas = {}
    for side, client in clients.items():
        answer = client.call("GetTableSchema", K.GetTableSchemaRequest(), entry=tables[side])
        schemas[side] = pa.ipc.read_schema(pa.py_buffer(answer.schema.arrow_schema))
    assert schemas["ours"].equals(schemas["reference"], check_metadata=True)
    for side, client in clients.items():
        parts = client.call("ScanTable", K.ScanTableRequest(), entry=tables[side])
        rows = pa.Table.from_batches([b for p in parts for b in read_dataframe_part(p.dataframe_part).to_batches()])
        assert rows.schema.equals(schemas["reference"], check_metadata=True), side
        kinds = dict(zip(rows.column("name").to_pylist(), rows.column("entry_kind").to_pylist(), strict=True))
        assert {n: k for n, k in kinds.items() if not rerun_own(n)} == listed["reference"], side

    for name in ("fleet_points", "fleet_props", "fleet_merge"):
        got = {}
        for side, client in clients.items():
            entry = dataset_ids(client)[name]
            got[side] = client.call("ReadDatasetEntry", K.ReadDatasetEntryRequest(), entry=entry).dataset
            assert got[side].HasField("dataset_details"), side
            assert got[side].dataset_handle.HasField("dataset_url"), side
        assert got["ours"].details.entry_kind == got["reference"].details.entry_kind
        assert got["ours"].dataset_handle.dataset_kind == got["reference"].dataset_handle.dataset_kind
        assert got["ours"].dataset_handle.store_kind == got["reference"].dataset_handle.store_kind

    capabilities = {s: set(c.call("WhoAmI", K.WhoAmIRequest()).capabilities.capabilities) for s, c in clients.items()}
    assert capabilities["ours"] <= capabilities["reference"]


@pytest.mark.sdk
def test_refusals_have_rerun_servers_status_codes(served_client: Redap, scenes_reference: Redap):
    for client in (scenes_reference, served_client):
        table, dataset = table_ids(client)["__entries"], dataset_ids(client)["fleet_props"]
        body = Tuid.parse(table).entry_id()
        unspecified = K.EntryFilter(entry_kinds=[K.ENTRY_KIND_UNSPECIFIED])
        calls: dict[str, tuple[str, object, str | None]] = {
            "unspecified kind": ("FindEntries", K.FindEntriesRequest(filter=unspecified), None),
            "legacy unspecified kind": (
                "FindEntries",
                K.FindEntriesRequest(filter=K.EntryFilter(entry_kind=K.ENTRY_KIND_UNSPECIFIED)),
                None,
            ),
            "table named by neither": ("ReadTableEntry", K.ReadTableEntryRequest(), None),
            "header and body disagree": (
                "ScanTable",
                K.ScanTableRequest(table_id=Tuid.parse(dataset).entry_id()),
                table,
            ),
            "a dataset read as a table": ("ReadTableEntry", K.ReadTableEntryRequest(), dataset),
            "an unknown dataset": ("ReadDatasetEntry", K.ReadDatasetEntryRequest(), str(Tuid(1, 2))),
            "a malformed entry id": ("ReadDatasetEntry", K.ReadDatasetEntryRequest(), "xyz"),
            "the table by its body (old clients)": ("GetTableSchema", K.GetTableSchemaRequest(table_id=body), None),
        }
        codes = {what: status_of(client, *call) for what, call in calls.items()}
        assert codes == {
            "unspecified kind": grpc.StatusCode.INVALID_ARGUMENT,
            "legacy unspecified kind": grpc.StatusCode.INVALID_ARGUMENT,
            "table named by neither": grpc.StatusCode.INVALID_ARGUMENT,
            "header and body disagree": grpc.StatusCode.INVALID_ARGUMENT,
            "a dataset read as a table": grpc.StatusCode.NOT_FOUND,
            "an unknown dataset": grpc.StatusCode.NOT_FOUND,
            "a malformed entry id": grpc.StatusCode.INVALID_ARGUMENT,
            "the table by its body (old clients)": grpc.StatusCode.OK,
        }, client


@dataclass(frozen=True)
class Guarded:
    """`fleet serve` with auth on, holding the scenes, and tokens for it."""

    server: LiveServer
    admin: str
    reader: str

    @property
    def url(self) -> str:
        return f"rerun+http://127.0.0.1:{self.server.grpc_port}"


@pytest.fixture(scope="module")
def guarded(scenes: dict[str, Recording], tmp_path_factory: pytest.TempPathFactory) -> Iterator[Guarded]:
    data = tmp_path_factory.mktemp("redap-guarded") / "data"
    with serving(scenes, data, auth="on") as server:
        admin = (data / "admin.token").read_text().strip()
        created = subprocess.run(
            [FLEET, "tokens", "create", "--scope", "read", "--name", "alice", "--api-url", server.url],
            capture_output=True,
            text=True,
            timeout=60,
            env={**os.environ, "FLEET_TOKEN": admin},
        )
        assert created.returncode == 0, created.stderr
        yield Guarded(server, admin, created.stdout.strip())


@pytest.fixture
def no_ambient_token(monkeypatch: pytest.MonkeyPatch) -> None:
    """The SDK falls back on REDAP_TOKEN: none here, so a call without `token=` is anonymous."""
    monkeypatch.delenv("REDAP_TOKEN", raising=False)


@pytest.mark.sdk
@pytest.mark.usefixtures("no_ambient_token")
def test_with_auth_on_anonymous_callers_are_unauthenticated(guarded: Guarded):
    import rerun as rr

    anonymous = Redap(guarded.server.grpc_port)
    try:
        for rpc, request in (
            ("WhoAmI", K.WhoAmIRequest()),
            ("FindEntries", K.FindEntriesRequest(filter=K.EntryFilter())),
            ("ScanTable", K.ScanTableRequest(table_id=ENTRIES_TABLE_ID.entry_id())),
        ):
            assert status_of(anonymous, rpc, request) == grpc.StatusCode.UNAUTHENTICATED, rpc
    finally:
        anonymous.close()
    with pytest.raises(Exception, match=r"(?i)unauthenticated"):
        rr.catalog.CatalogClient(guarded.url).dataset_names()


@pytest.mark.sdk
@pytest.mark.usefixtures("no_ambient_token")
def test_a_read_token_browses_the_catalog_with_the_sdk(guarded: Guarded):
    import rerun as rr

    client = rr.catalog.CatalogClient(guarded.url, token=guarded.reader)
    assert client.version_info().version == services.__version__
    assert sorted(client.dataset_names()) == ["fleet_merge", "fleet_points", "fleet_props"]
    assert [d.name for d in client.datasets()] == sorted(client.dataset_names())
    dataset = client.get_dataset("fleet_merge")
    raw = Redap(guarded.server.grpc_port, token=guarded.reader)
    try:
        assert str(dataset.id) == dataset_ids(raw)["fleet_merge"]
    finally:
        raw.close()
    assert sorted(dataset.segment_ids()) == ["rec-merge-a", "rec-merge-b"]
    table = client.get_dataset("fleet_points").segment_table().to_arrow_table()
    assert table.column("rerun_segment_id").to_pylist() == ["rec-points"]
    assert table.column("property:depot:tier").to_pylist() == [["warm"]]


@pytest.mark.sdk
@pytest.mark.parametrize(("who", "can_write"), [("reader", False), ("admin", True)])
def test_who_am_i_tells_the_truth_about_writing(guarded: Guarded, who: str, can_write: bool):
    client = Redap(guarded.server.grpc_port, token=getattr(guarded, who))
    try:
        answer = client.call("WhoAmI", K.WhoAmIRequest())
    finally:
        client.close()
    assert (answer.can_read, answer.can_write) == (True, can_write)
    assert answer.user_id  # the token's subject
    if who == "reader":
        assert answer.user_id == "alice"
    assert list(answer.capabilities.capabilities) == ["dataset:find_chunks"]
