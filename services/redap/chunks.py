"""Chunk keys and FetchChunks: a chunk's bytes straight from its hot file or its sealed object by
range, never re-encoded."""

from __future__ import annotations

from collections.abc import Iterator

from core.errors import UnimplementedError
from services.auth.scopes import Principal
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2


def fetch_chunks(
    depot: Depot, principal: Principal, request: cloud_pb2.FetchChunksRequest
) -> Iterator[cloud_pb2.FetchChunksResponse]:
    raise UnimplementedError("fetch_chunks is not served yet")
