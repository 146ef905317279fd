"""Chunk keys and FetchChunks: a chunk's bytes straight from its hot file or its sealed object by
range, never re-encoded.

A chunk key is Rerun's `ChunkKey` message, which clients treat as opaque and hand back to
FetchChunks: the chunk's id and an `RrdChunkLocation` whose `url` is `fleet:RUN` and whose
offset and length are those of the chunk's whole frame in the run's recording (its 16-byte
message header included, as Rerun's direct-URL readers expect)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from core.errors import InvalidArgumentError, UnimplementedError
from services.auth.scopes import Principal
from services.redap.depot import Depot
from services.redap.pb import cloud_pb2
from services.redap.tuid import Tuid

RUN_URL_PREFIX = "fleet:"


@dataclass(frozen=True)
class ChunkLocation:
    run_id: str
    offset: int  # of the chunk's frame (its message header) in the run's recording
    length: int  # of the whole frame


def chunk_key(run_id: str, offset: int, length: int, chunk_id: bytes) -> bytes:
    """The key FindChunks and GetRrdManifest hand out for a chunk (`chunk_id`: its 16 bytes)."""
    location = cloud_pb2.RrdChunkLocation(url=f"{RUN_URL_PREFIX}{run_id}", offset=offset, length=length)
    key = cloud_pb2.ChunkKey(
        chunk_id=Tuid(int.from_bytes(chunk_id[:8], "big"), int.from_bytes(chunk_id[8:], "big")).to_proto(),
        data_source_kind=cloud_pb2.DATA_SOURCE_KIND_RRD,
        location=location.SerializeToString(),
    )
    return key.SerializeToString()


def parse_chunk_key(key: bytes) -> ChunkLocation:
    """Where a chunk key a client sent points; INVALID_ARGUMENT if it is none of ours."""
    try:
        parsed = cloud_pb2.ChunkKey.FromString(key)
        location = cloud_pb2.RrdChunkLocation.FromString(parsed.location)
    except Exception as exc:  # protobuf's DecodeError and friends: the client sent something else
        raise InvalidArgumentError("a chunk_key is not one this depot handed out: ask GetRrdManifest again") from exc
    if not location.url.startswith(RUN_URL_PREFIX) or location.length <= 0:
        raise InvalidArgumentError("a chunk_key is not one this depot handed out: ask GetRrdManifest again")
    return ChunkLocation(location.url[len(RUN_URL_PREFIX) :], location.offset, location.length)


def fetch_chunks(
    depot: Depot, principal: Principal, request: cloud_pb2.FetchChunksRequest
) -> Iterator[cloud_pb2.FetchChunksResponse]:
    raise UnimplementedError("fetch_chunks is not served yet")
