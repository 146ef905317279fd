"""The catalog: the server's version, who the caller is, the datasets (one per application id, and
one per snapshot version, `snapshots.py`) and the `__entries` system table that Rerun's viewer
shows as the server's landing page."""

from __future__ import annotations

import datetime as dt
import platform
import re
from collections.abc import Iterator
from dataclasses import dataclass
from typing import NoReturn
from urllib.parse import quote

import pyarrow as pa
from google.protobuf import any_pb2
from google.protobuf.timestamp_pb2 import Timestamp

import services
from catalog import queries
from catalog.db import session_scope
from catalog.models import Dataset
from core.clock import aware
from core.errors import InvalidArgumentError, NotFoundError, UnimplementedError
from core.ids import new_entry_id
from services.auth.scopes import Principal, Scope
from services.redap.dataframe import dataframe_part, schema_proto
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.snapshots import SnapshotVersion, find_dataset, snapshot_versions
from services.redap.tuid import Tuid, epoch_ns
from services.rrd.pb import common_pb2

CRATE_NAME = "fleet-telemetry"  # the package's name, where Rerun's servers name their crate
# What WhoAmI advertises: only what this depot answers (Rerun's clients pick their calls by it).
CAPABILITIES = ("dataset:find_chunks",)

ENTRIES_TABLE = "__entries"
# The system table's id never changes: clients keep entry ids in URLs. Made like a dataset's, from
# its name and a fixed time (the table's "creation").
ENTRIES_TABLE_CREATED = dt.datetime(2026, 1, 1, tzinfo=dt.UTC)
ENTRIES_TABLE_ID = Tuid.parse(new_entry_id(ENTRIES_TABLE, int(ENTRIES_TABLE_CREATED.timestamp()) * 10**9))

# Kinds a filter without any asks for: what Rerun's own server answers then (assets left out).
DEFAULT_KINDS = frozenset(
    {cloud_pb2.ENTRY_KIND_DATASET, cloud_pb2.ENTRY_KIND_TABLE, cloud_pb2.ENTRY_KIND_BLUEPRINT_DATASET}
)

# `__entries` as Rerun's server types it (checked against `rerun server` 0.41 by the golden tests).
ENTRIES_SCHEMA = pa.schema(
    [
        pa.field("id", pa.binary(16), nullable=False),
        pa.field("name", pa.utf8(), nullable=False),
        pa.field(
            "entry_kind", pa.uint8(), nullable=False, metadata={"rerun:component_type": "rerun.components.EntryKind"}
        ),
        pa.field("created_at", pa.timestamp("ns"), nullable=False),
        pa.field("updated_at", pa.timestamp("ns"), nullable=False),
    ]
)
ENTRIES_PART_ROWS = 4096  # rows per ScanTable response


@dataclass(frozen=True)
class Entry:
    """One entry of the catalog: a dataset or the system table."""

    id: Tuid
    name: str
    kind: int  # a cloud_pb2.EntryKind
    created_at: dt.datetime
    updated_at: dt.datetime
    snapshot: bool = False  # a snapshot version's

    def details(self) -> cloud_pb2.EntryDetails:
        return cloud_pb2.EntryDetails(
            id=self.id.entry_id(),
            name=self.name,
            entry_kind=self.kind,  # type: ignore[arg-type]
            created_at=_timestamp(self.created_at),
            updated_at=_timestamp(self.updated_at),
        )


def _timestamp(value: dt.datetime) -> Timestamp:
    stamp = Timestamp()
    stamp.FromDatetime(aware(value))
    return stamp


def depot_url(depot: Depot, path: str) -> str:
    """An absolute URL of the depot's REST API for `path` (Rerun's clients parse the URLs they are
    given): under FLEET_PUBLIC_URL, else `fleet://` and the path, naming this depot without an address."""
    base = depot.public_url.rstrip("/") if depot.public_url else "fleet://"
    return f"{base}{path}"


# --- the server ------------------------------------------------------------------------------


def _semantic_version(text: str) -> common_pb2.SemanticVersion:
    found = re.match(r"(\d+)\.(\d+)\.(\d+)", text)
    if found is None:
        return common_pb2.SemanticVersion()
    major, minor, patch = (int(n) for n in found.groups())
    return common_pb2.SemanticVersion(major=major, minor=minor, patch=patch)


def version() -> cloud_pb2.VersionResponse:
    """The depot's version (what `CatalogClient.version_info()` shows); no features flags, as the
    depot consumes none of the optional request fields they announce."""
    return cloud_pb2.VersionResponse(
        version=services.__version__,
        build_info=common_pb2.BuildInfo(
            crate_name=CRATE_NAME,
            version=_semantic_version(services.__version__),
            target_triple=f"{platform.machine()}-{platform.system().lower()}",
            is_debug_build=False,
        ),
    )


def who_am_i(depot: Depot, principal: Principal) -> cloud_pb2.WhoAmIResponse:
    """Who the token is and what it may do; the capabilities always set (unset means "a server too
    old to say" to Rerun's clients, which then try calls the depot does not answer)."""
    return cloud_pb2.WhoAmIResponse(
        user_id=principal.subject,
        can_read=principal.allows(Scope.READ),
        can_write=principal.allows(Scope.WRITE),
        capabilities=cloud_pb2.ServerCapabilities(capabilities=CAPABILITIES),
    )


# --- entries ---------------------------------------------------------------------------------


def catalog_entries(depot: Depot) -> list[Entry]:
    """Every entry: the applications' datasets, the snapshot versions, then the system table
    (updated when a dataset last was)."""
    with session_scope(depot.catalog) as session:
        datasets = [_dataset_entry(d) for d in queries.datasets(session)]
        datasets += [_snapshot_entry(v) for v in snapshot_versions(session)]
    updated = max([ENTRIES_TABLE_CREATED, *(d.updated_at for d in datasets)])
    table = Entry(ENTRIES_TABLE_ID, ENTRIES_TABLE, cloud_pb2.ENTRY_KIND_TABLE, ENTRIES_TABLE_CREATED, updated)
    return [*datasets, table]


def _dataset_entry(dataset: Dataset) -> Entry:
    return Entry(
        Tuid.parse(dataset.entry_id),
        dataset.name,
        cloud_pb2.ENTRY_KIND_DATASET,
        aware(dataset.created_at),
        aware(dataset.updated_at),
    )


def _snapshot_entry(version: SnapshotVersion) -> Entry:
    at = version.created_at  # never updated
    return Entry(version.entry_id, version.entry_name, cloud_pb2.ENTRY_KIND_DATASET, at, at, snapshot=True)


def wanted_kinds(entry_filter: cloud_pb2.EntryFilter) -> frozenset[int]:
    """The kinds a filter asks for: `entry_kinds` if given, else the legacy `entry_kind`, else the
    default set; UNSPECIFIED asked for is INVALID_ARGUMENT, as Rerun's server answers."""
    if entry_filter.entry_kinds:
        if cloud_pb2.ENTRY_KIND_UNSPECIFIED in entry_filter.entry_kinds:
            raise InvalidArgumentError("entry_kinds must not hold ENTRY_KIND_UNSPECIFIED: name the kinds wanted")
        return frozenset(entry_filter.entry_kinds)
    if entry_filter.HasField("entry_kind"):
        if entry_filter.entry_kind == cloud_pb2.ENTRY_KIND_UNSPECIFIED:
            raise InvalidArgumentError("entry_kind ENTRY_KIND_UNSPECIFIED matches nothing: name a kind or leave it out")
        return frozenset({entry_filter.entry_kind})
    return DEFAULT_KINDS


def _matches(entry: Entry, entry_filter: cloud_pb2.EntryFilter, kinds: frozenset[int]) -> bool:
    if entry.kind not in kinds:
        return False
    if entry_filter.HasField("name") and entry.name != entry_filter.name:
        return False
    if entry_filter.HasField("id"):
        # An id without its TUID matches nothing (Rerun's filter contract: malformed, not an error).
        wanted = entry_filter.id
        return wanted.HasField("id") and Tuid.from_proto(wanted.id) == entry.id
    return True


def find_entries(
    depot: Depot, principal: Principal, request: cloud_pb2.FindEntriesRequest
) -> cloud_pb2.FindEntriesResponse:
    kinds = wanted_kinds(request.filter)
    found = [e for e in catalog_entries(depot) if _matches(e, request.filter, kinds)]
    if request.filter.HasField("name") and any(e.snapshot for e in found):
        found = [e for e in found if e.snapshot]  # an application named as a version is: the version's name
    return cloud_pb2.FindEntriesResponse(entries=[e.details() for e in found])


def read_dataset_entry(depot: Depot, principal: Principal, entry: Tuid) -> cloud_pb2.ReadDatasetEntryResponse:
    if entry == ENTRIES_TABLE_ID:
        raise NotFoundError(f"entry {entry} is the {ENTRIES_TABLE} table, not a dataset: read it with ReadTableEntry")
    with session_scope(depot.catalog) as session:
        dataset = find_dataset(session, entry)
        if isinstance(dataset, SnapshotVersion):
            found = _snapshot_entry(dataset)
            path = f"/v1/datasets/{quote(dataset.name, safe='')}/{dataset.version}"
        else:
            found = _dataset_entry(dataset)
            path = f"/v1/runs?application={quote(found.name, safe='')}"
    answer = cloud_pb2.DatasetEntry(
        details=found.details(),
        dataset_handle=common_pb2.DatasetHandle(
            entry_id=entry.entry_id(),
            dataset_kind=common_pb2.DATASET_KIND_RECORDING,
            store_kind=common_pb2.STORE_KIND_RECORDING,  # what clients before dataset kinds read
            dataset_url=depot_url(depot, path),  # required by the SDK
        ),
    )
    answer.dataset_details.SetInParent()  # present though empty: Rerun's viewer refuses an entry without
    return cloud_pb2.ReadDatasetEntryResponse(dataset=answer)


def refuse_write(depot: Depot, principal: Principal, entry: Tuid | None, rpc: str) -> NoReturn:
    """A write to an entry (register, unregister, delete, update, segment properties, maintenance):
    FAILED_PRECONDITION for a snapshot version, which never changes; the depot serves no writes to
    other entries either (UNIMPLEMENTED)."""
    if entry is not None and entry != ENTRIES_TABLE_ID:
        with session_scope(depot.catalog) as session:
            try:
                found = find_dataset(session, entry)
            except NotFoundError:
                found = None
        if isinstance(found, SnapshotVersion):
            raise found.immutable(rpc)
    raise UnimplementedError(f"this depot does not serve {rpc}: its datasets are written by ingest")


# --- the __entries system table --------------------------------------------------------------


def table_id(header: Tuid | None, body: common_pb2.EntryId | None) -> Tuid:
    """The table a call names: its `x-rerun-entry-id` header, or for clients from before that
    header, the request's id field; both given and different is INVALID_ARGUMENT naming both."""
    from_body = Tuid.from_proto(body.id) if body is not None and body.HasField("id") else None
    if header is not None and from_body is not None and header != from_body:
        raise InvalidArgumentError(
            f"the x-rerun-entry-id header names entry {header} but the request body names {from_body}: "
            "send one of them, or the same id in both"
        )
    found = header or from_body
    if found is None:
        raise InvalidArgumentError("no table named: send its entry id in the x-rerun-entry-id header")
    return found


def _system_table(entry: Tuid) -> None:
    if entry != ENTRIES_TABLE_ID:
        raise NotFoundError(
            f"no table has entry id {entry}: the depot's one table is {ENTRIES_TABLE} ({ENTRIES_TABLE_ID}); "
            "datasets are read with ReadDatasetEntry"
        )


def read_table_entry(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.ReadTableEntryRequest
) -> cloud_pb2.ReadTableEntryResponse:
    _system_table(entry)
    table = next(e for e in catalog_entries(depot) if e.id == ENTRIES_TABLE_ID)
    provider = any_pb2.Any()
    provider.Pack(cloud_pb2.SystemTable(kind=cloud_pb2.SYSTEM_TABLE_KIND_ENTRIES), type_url_prefix="/")
    answer = cloud_pb2.TableEntry(details=table.details(), provider_details=provider)
    answer.table_details.SetInParent()
    return cloud_pb2.ReadTableEntryResponse(table=answer)


def table_schema(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.GetTableSchemaRequest
) -> cloud_pb2.GetTableSchemaResponse:
    _system_table(entry)
    return cloud_pb2.GetTableSchemaResponse(schema=schema_proto(ENTRIES_SCHEMA))


def entries_table(entries: list[Entry]) -> pa.Table:
    return pa.table(
        [
            pa.array([e.id.to_bytes() for e in entries], pa.binary(16)),
            pa.array([e.name for e in entries], pa.utf8()),
            pa.array([e.kind for e in entries], pa.uint8()),
            pa.array([epoch_ns(e.created_at) for e in entries], pa.int64()).cast(pa.timestamp("ns")),
            pa.array([epoch_ns(e.updated_at) for e in entries], pa.int64()).cast(pa.timestamp("ns")),
        ],
        schema=ENTRIES_SCHEMA,
    )


def scan_table(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.ScanTableRequest
) -> Iterator[cloud_pb2.ScanTableResponse]:
    _system_table(entry)
    entries = catalog_entries(depot)
    for start in range(0, len(entries), ENTRIES_PART_ROWS):
        part = entries_table(entries[start : start + ENTRIES_PART_ROWS])
        yield cloud_pb2.ScanTableResponse(dataframe_part=dataframe_part(part))
