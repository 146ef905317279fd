"""Opening a segment: its RRD manifest (the sealed footer's, or the hot run's chunk index) with
chunk keys, and its assets."""

from __future__ import annotations

from collections.abc import Iterator

from core.errors import UnimplementedError
from services.auth.scopes import Principal
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid


def rrd_manifest(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.GetRrdManifestRequest
) -> Iterator[cloud_pb2.GetRrdManifestResponse]:
    raise UnimplementedError("rrd_manifest is not served yet")


def assets(
    depot: Depot, principal: Principal, entry: Tuid, request: cloud_pb2.GetAssetsForSegmentRequest
) -> Iterator[cloud_pb2.GetAssetsForSegmentResponse]:
    raise UnimplementedError("assets is not served yet")
