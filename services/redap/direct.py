"""Direct reads from the bucket (FLEET_DIRECT_READS=presigned), as Rerun's own cloud serves them: a
sealed run's candidate rows (FindChunks, QueryDataset) carry a presigned GET URL of its
`recording.rrd` in the warm bucket, and the client reads the chunks' byte ranges (their keys'
offset and length, message header included) from the bucket itself, not through FetchChunks.

Only a whole sealed run's rows get one: a hot run's chunks are in this node's file, and a snapshot
episode's are served under ids of their own (`chunks.episode_chunk_id`), which the bytes in the
bucket do not carry. A URL names one object, lasts FLEET_DIRECT_URL_TTL_S (15 minutes at most), and
holds a signature, never a credential's secret. Rerun's viewer still fetches with FetchChunks: only
its manifests' keys, which it hands back, are read through the depot."""

from __future__ import annotations

import time
from dataclasses import dataclass

from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.sources import IndexedRecordingSource
from services.sealed.write import RECORDING
from services.settings import DirectReads
from services.storage.objectstore import supports_presigned


@dataclass(frozen=True)
class DirectUrl:
    url: str
    expires_at_ns: int  # nanoseconds since the epoch, as Rerun's tables hold times


def wanted_by_find_chunks(request: cloud_pb2.FindChunksRequest) -> bool:
    """FindChunks' `direct_url_mode`: signed URLs unless the client says OMIT (UNSIGNED ones, for
    clients holding the bucket's credentials, are not handed out: the mode is an upper bound)."""
    return request.direct_url_mode in (cloud_pb2.DIRECT_URL_MODE_UNSPECIFIED, cloud_pb2.DIRECT_URL_MODE_SIGNED)


def wanted_by_query_dataset(request: cloud_pb2.QueryDatasetRequest) -> bool:
    return request.generate_direct_urls and not request.unsigned_direct_urls


def direct_url(depot: Depot, source: IndexedRecordingSource) -> DirectUrl | None:
    """A presigned URL of the sealed run's recording, or None when its rows are read through the
    depot (direct reads off, a hot run, a store that cannot presign)."""
    settings = depot.node.settings
    store = depot.warm
    if settings.direct_reads != DirectReads.PRESIGNED or source.prefix is None or not supports_presigned(store):
        return None
    ttl = settings.direct_url_ttl_s
    issued_ns = time.time_ns()  # the signature's own clock, not the depot's (which tests may set)
    url = store.presigned_get(f"{source.prefix}/{RECORDING}", ttl)
    return DirectUrl(url, issued_ns + ttl * 1_000_000_000)
