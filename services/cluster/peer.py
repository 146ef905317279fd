"""Reads of a hot run asked of the node that owns it, over its peer port (`fleet.peer.v1.Peer`):
the run's recording as a download would stream it, and the agent's `held` question. Requests are
JSON; a recording comes back as its bytes, a held answer as JSON. Served by `services.api.peer`."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from typing import Any

import grpc

from core.errors import UnavailableError
from services.cluster.ownership import Owner
from services.cluster.relay import Channels, Metadata, PeerUnavailable, refusal_of

SERVICE = "fleet.peer.v1.Peer"
READ_HOT = f"/{SERVICE}/ReadHot"
HELD = f"/{SERVICE}/Held"


def _unavailable(owner: Owner) -> UnavailableError:
    return UnavailableError(
        f"run {owner.run_id} is being written on node {owner.node_id}, which does not answer at {owner.peer_addr}: "
        "try again in a few seconds"
    )


async def read_hot(
    channels: Channels, owner: Owner, request: dict[str, Any], metadata: Metadata
) -> AsyncIterator[bytes]:
    """The owner's answer to a recording download, piece by piece."""
    try:
        channel = await channels.ready(owner.peer_addr)
    except PeerUnavailable:
        raise _unavailable(owner) from None
    method = channel.unary_stream(READ_HOT, request_serializer=None, response_deserializer=None)
    call = method(json.dumps(request).encode(), metadata=tuple(metadata))
    try:
        async for piece in call:
            yield piece
    except grpc.aio.AioRpcError as exc:
        raise refusal_of(exc, owner) from None


async def held(channels: Channels, owner: Owner, request: dict[str, Any], metadata: Metadata) -> dict[str, Any]:
    """The owner's answer to `POST /v1/runs/RUN/held`."""
    try:
        channel = await channels.ready(owner.peer_addr)
    except PeerUnavailable:
        raise _unavailable(owner) from None
    method = channel.unary_unary(HELD, request_serializer=None, response_deserializer=None)
    try:
        answer = await method(json.dumps(request).encode(), metadata=tuple(metadata), timeout=60)
    except grpc.aio.AioRpcError as exc:
        raise refusal_of(exc, owner) from None
    return dict(json.loads(answer))
