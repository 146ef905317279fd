"""Messages handed to the node that owns their run, over its peer port: the same
`MessageProxyService/WriteMessages` call robots make, each request passed on byte for byte.

`Relay`: one source's remaining messages (a stream or an upload that reached a node that does not own
its run), on the event loop. `hand_over`: a whole hot copy, from a worker thread (a node that filed
chunks of a run another node owns: while the catalog did not answer, or after its run was taken
over). The owner's answer (what was new) comes back in the call's trailing metadata; its refusals
come back with their own code and message.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import grpc

from core.errors import ErrorCode, FleetError, UnavailableError
from sdk_client.grpc_status import ended, keep_status, server_status
from services.cluster.ownership import Owner
from services.rrd.messages import ArrowMessage, BlueprintActivationMessage, Event, StoreInfoMessage
from services.rrd.protowire import log_msg_envelope

WRITE_METHOD = "/rerun.sdk_comms.v1alpha1.MessageProxyService/WriteMessages"
RELAYED_BY = "fleet-relayed-by"  # metadata: the node that relays (the owner files, never relays again)
SOURCE_KIND = "fleet-source"  # metadata: "live" (a stream) or "upload"
# metadata: the relaying node's peer token (signed with the depot's key, naming that node): what
# makes the two keys above believed. A client may send none of the three (refused).
PEER_CREDENTIAL = "fleet-peer"
INTERNAL_KEYS = (RELAYED_BY, SOURCE_KIND, PEER_CREDENTIAL)
REPORT = "fleet-report"  # trailing metadata: the owner's IngestReport as JSON
ERROR_CODE = "fleet-error-code"  # trailing metadata of a refusal: its ErrorCode
CONNECT_TIMEOUT_S = 3.0
MAX_HANDED_MESSAGE = 1 << 30  # a hot copy holds only messages this depot accepted
Metadata = Sequence[tuple[str, str]]


class RelayedError(FleetError):
    """A refusal of the owning node, passed on with its code and message."""

    def __init__(self, code: ErrorCode, message: str) -> None:
        super().__init__(message)
        self.code = code


class PeerUnavailable(Exception):
    """The owning node could not be reached."""


def request_of(event: Event) -> bytes | None:
    """The WriteMessagesRequest carrying `event`; None for what a stream does not carry (its header)."""
    if isinstance(event, StoreInfoMessage | ArrowMessage | BlueprintActivationMessage):
        return log_msg_envelope(int(event.kind), event.raw)
    return None


def metadata_value(metadata: Any, key: str) -> str | None:
    """The value of `key` in a call's metadata (invocation or trailing), as text; None if absent."""
    for k, v in metadata or ():
        if k == key:
            return v.decode() if isinstance(v, bytes) else str(v)
    return None


def refusal_of(exc: grpc.RpcError, owner: Owner) -> FleetError:
    """The owner's refusal as ours, or UNAVAILABLE if the call broke on the way."""
    code = metadata_value(exc.trailing_metadata(), ERROR_CODE)  # type: ignore[attr-defined]
    if code is not None and code in ErrorCode.__members__:
        return RelayedError(ErrorCode[code], str(exc.details() or code))  # type: ignore[attr-defined]
    return UnavailableError(
        f"node {owner.node_id}, which owns run {owner.run_id}, stopped answering ({exc.code().name}): "  # type: ignore[attr-defined]
        "send again (chunks the depot holds are skipped)"
    )


def report_of(trailing: Any) -> dict[str, Any]:
    text = metadata_value(trailing, REPORT)
    return dict(json.loads(text)) if text else {}


def peer_channel_options(max_message_size: int) -> list[tuple[str, int]]:
    """Messages as large as robots may send; keepalive pings so a dead owner is noticed."""
    return [
        ("grpc.max_send_message_length", max_message_size + 1024),
        ("grpc.max_receive_message_length", max_message_size + 1024),
        ("grpc.keepalive_time_ms", 10_000),
        ("grpc.keepalive_timeout_ms", 10_000),
        ("grpc.keepalive_permit_without_calls", 1),
    ]


class Channels:
    """One channel per peer address, kept for reuse."""

    def __init__(self, options: list[tuple[str, int]]) -> None:
        self.options = options
        self._channels: dict[str, grpc.aio.Channel] = {}

    async def ready(self, addr: str) -> grpc.aio.Channel:
        """The channel to `addr`, connected; PeerUnavailable if it does not connect in time. Several
        callers may wait on one channel: the first to give up closes it, the others see it closed."""
        found = self._channels.get(addr)
        channel = found if found is not None else grpc.aio.insecure_channel(addr, options=self.options)
        self._channels[addr] = channel
        try:
            await asyncio.wait_for(channel.channel_ready(), CONNECT_TIMEOUT_S)
        except (TimeoutError, grpc.aio.AioRpcError, grpc.aio.UsageError) as exc:
            still_cached = self._channels.get(addr) is channel
            if still_cached:
                del self._channels[addr]
                await channel.close()
            raise PeerUnavailable(addr) from exc
        return channel

    async def close(self) -> None:
        for channel in self._channels.values():
            await channel.close()
        self._channels.clear()


class Relay:
    """The rest of one source's messages, sent to the run's owner as they come."""

    def __init__(self, owner: Owner, call: Any) -> None:
        self.owner = owner
        self._call = call

    @classmethod
    async def open(cls, channels: Channels, owner: Owner, metadata: Metadata) -> Relay:
        channel = await channels.ready(owner.peer_addr)
        method = channel.stream_unary(WRITE_METHOD, request_serializer=None, response_deserializer=None)
        return cls(owner, keep_status(method(metadata=tuple(metadata))))

    async def send(self, request: bytes | memoryview) -> None:
        try:  # grpc.aio writes bytes only (the front hands large requests over as views)
            await self._call.write(request if isinstance(request, bytes) else bytes(request))
        except grpc.aio.AioRpcError as exc:  # the owner's refusal, when it is one, is in the call's status
            raise refusal_of(await ended(self._call, exc), self.owner) from None
        except asyncio.InvalidStateError:  # the call already ended: its status says why
            await self.finish()
            raise UnavailableError(f"node {self.owner.node_id} ended the relay of run {self.owner.run_id}") from None

    async def finish(self) -> dict[str, Any]:
        """End the call and wait for the owner's answer: what it filed."""
        try:
            await self._call.done_writing()
            await self._call
            return report_of(await self._call.trailing_metadata())
        except grpc.aio.AioRpcError as exc:
            raise refusal_of(server_status(self._call, exc), self.owner) from None

    def cancel(self) -> None:
        self._call.cancel()


def hand_over(owner: Owner, events: Iterable[Event], metadata: Metadata, timeout_s: float) -> dict[str, Any]:
    """Send a hot copy's messages to their run's owner; its report of what was new."""

    def requests() -> Iterator[bytes]:
        for event in events:
            request = request_of(event)
            if request is not None:
                yield request

    with grpc.insecure_channel(owner.peer_addr, options=peer_channel_options(MAX_HANDED_MESSAGE)) as channel:
        method = channel.stream_unary(WRITE_METHOD, request_serializer=None, response_deserializer=None)
        try:
            _, call = method.with_call(requests(), metadata=tuple(metadata), timeout=timeout_s)
        except grpc.RpcError as exc:
            raise refusal_of(exc, owner) from None
        return report_of(call.trailing_metadata())
