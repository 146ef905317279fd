"""The catalog: the server's version, who the caller is, the datasets (one per application id) and
the `__entries` system table."""

from __future__ import annotations

from collections.abc import Iterator

from core.errors import UnimplementedError
from services.auth.scopes import Principal
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid


def version() -> cloud_pb2.VersionResponse:
    raise UnimplementedError("version is not served yet")


def who_am_i(depot: Depot, principal: Principal) -> cloud_pb2.WhoAmIResponse:
    raise UnimplementedError("who_am_i is not served yet")


def find_entries(
    depot: Depot, principal: Principal, request: cloud_pb2.FindEntriesRequest
) -> cloud_pb2.FindEntriesResponse:
    raise UnimplementedError("find_entries is not served yet")


def read_dataset_entry(depot: Depot, principal: Principal, entry: Tuid) -> cloud_pb2.ReadDatasetEntryResponse:
    raise UnimplementedError("read_dataset_entry is not served yet")


def read_table_entry(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.ReadTableEntryRequest
) -> cloud_pb2.ReadTableEntryResponse:
    raise UnimplementedError("read_table_entry is not served yet")


def table_schema(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.GetTableSchemaRequest
) -> cloud_pb2.GetTableSchemaResponse:
    raise UnimplementedError("table_schema is not served yet")


def scan_table(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.ScanTableRequest
) -> Iterator[cloud_pb2.ScanTableResponse]:
    raise UnimplementedError("scan_table is not served yet")
