"""A dataset's segment table: one row per run, with Rerun's columns and the fleet's."""

from __future__ import annotations

from collections.abc import Iterator

from core.errors import UnimplementedError
from services.auth.scopes import Principal
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid


def table_schema(depot: Depot, principal: Principal, entry: Tuid) -> cloud_pb2.GetSegmentTableSchemaResponse:
    raise UnimplementedError("table_schema is not served yet")


def scan(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.ScanSegmentTableRequest
) -> Iterator[cloud_pb2.ScanSegmentTableResponse]:
    raise UnimplementedError("scan is not served yet")
