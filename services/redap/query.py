"""Querying from the SDK: a dataset's schema and the chunks a query may need (a superset), from the chunk indexes."""

from __future__ import annotations

from collections.abc import Iterator

from core.errors import UnimplementedError
from services.auth.scopes import Principal
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid


def dataset_schema(depot: Depot, principal: Principal, entry: Tuid) -> cloud_pb2.GetDatasetSchemaResponse:
    raise UnimplementedError("dataset_schema is not served yet")


def find_chunks(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.FindChunksRequest
) -> Iterator[cloud_pb2.FindChunksResponse]:
    raise UnimplementedError("find_chunks is not served yet")


def query_dataset(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.QueryDatasetRequest
) -> Iterator[cloud_pb2.QueryDatasetResponse]:
    raise UnimplementedError("query_dataset is not served yet")
