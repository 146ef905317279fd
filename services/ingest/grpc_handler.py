"""gRPC `rerun.sdk_comms.v1alpha1.MessageProxyService.WriteMessages`: what the SDK's GrpcSink calls.

The handler only checks who calls (`stream_auth`), unwraps each request (`requests`: the inner message
bytes are taken as sent, never re-encoded), hands it to the ingest service and maps errors to a gRPC
status.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import AsyncIterator
from typing import NoReturn

import grpc

from core.errors import FleetError
from services.auth.metadata import GRPC
from services.auth.scopes import Scope
from services.auth.standing import GrantWatch
from services.auth.tokens import Auth
from services.cluster.relay import ERROR_CODE, REPORT
from services.ingest.replay import Message, read_response
from services.ingest.requests import decode_request
from services.ingest.routing import relay_source
from services.ingest.service import IngestService
from services.ingest.source import Source
from services.ingest.stream_auth import WRITERS, CallAuth, Metadata
from services.rrd.frames import UPGRADE_HINT
from services.rrd.messages import Event, StoreInfoMessage
from services.rrd.pb import sdk_comms_pb2

log = logging.getLogger(__name__)

SERVICE_NAME = "rerun.sdk_comms.v1alpha1.MessageProxyService"


class MessageProxy:
    def __init__(
        self,
        service: IngestService,
        auth: Auth | None = None,
        *,
        token_wait_s: float = 10.0,
        token_buffer_bytes: int = 16 << 20,
        token_buffer_total_bytes: int = 64 << 20,
    ) -> None:
        self.service = service
        self.auth = auth or Auth(enabled=False, keys=None, catalog=None)
        self.calls = CallAuth(
            self.auth, wait_s=token_wait_s, buffer_bytes=token_buffer_bytes, total_bytes=token_buffer_total_bytes
        )

    async def write_messages(
        self, requests: AsyncIterator[bytes], context: grpc.aio.ServicerContext
    ) -> sdk_comms_pb2.WriteMessagesResponse:
        metadata = context.invocation_metadata()
        relayed_by = None  # another node of the depot that passes this on
        by_property = self.calls.needs_property_token(metadata)
        try:
            relayed = self.calls.relayed(metadata, on_peer_port(context))
            relayed_by = relayed.node if relayed is not None else None
            principal = None if by_property else await self.calls.principal(metadata, *WRITERS)
            # A stream still waiting for its token counts among FLEET_MAX_STREAMS.
            source = self.service.open_source(
                live=relayed is None or relayed.live, robot=principal.robot if principal else None
            )
        except FleetError as exc:
            await refuse(context, exc, relayed_by)
        source.relayed_by = relayed_by
        received = 0  # bytes of requests so far: where errors are placed
        try:
            if by_property:
                admitted = await self.calls.await_property_token(requests, decode_request)
                source.robot = admitted.principal.robot  # bound before anything of the stream is filed
                for i, event in enumerate(admitted.held):
                    if isinstance(event, StoreInfoMessage):
                        await self.service.prepare(source, event)
                        if source.relay_to is not None and await self._relay(
                            source, metadata, admitted.held[i:], context
                        ):
                            return sdk_comms_pb2.WriteMessagesResponse()
                    self.service.accept(source, event)
                received = admitted.received
            read = context.read  # the hot path: nothing here but decoding and filing
            # read() rather than `async for`: the request iterator is an async generator around it,
            # a tenth of what a message costs gRPC
            while (request := await read()) is not grpc.aio.EOF:
                event = decode_request(request, received)  # a view: no copy
                # filed inline: no coroutine per message on the hot path
                if isinstance(event, StoreInfoMessage):  # the only message `prepare` looks at
                    await self.service.prepare(source, event)
                    if source.relay_to is not None and await self._relay(source, metadata, [event], context):
                        return sdk_comms_pb2.WriteMessagesResponse()
                self.service.accept(source, event)
                received += len(request)
        except FleetError as exc:
            await self.service.remove_dropped()  # a run the refusal dropped is gone once it is answered
            await refuse(context, exc, relayed_by)
        finally:
            report = await self.service.end_source(source)
        if relayed_by is not None:
            context.set_trailing_metadata(((REPORT, json.dumps(report.to_dict())),))
        return sdk_comms_pb2.WriteMessagesResponse()

    async def _relay(
        self, source: Source, metadata: Metadata, pending: list[Event], context: grpc.aio.ServicerContext
    ) -> bool:
        """Send the rest of the source to its run's owner: what it held back, `pending`, then every
        request as it comes. False if this node took the run over meanwhile (it files it itself)."""
        return await relay_source(self.service, self.auth, source, metadata, pending, _rest_of(context)) is not None

    async def read_messages(self, request: bytes, context: grpc.aio.ServicerContext) -> AsyncIterator[bytes]:
        """What `rerun --connect rerun+http://HOST:51234/proxy` calls: recent history, then live, for
        as long as the caller's token holds (checked again as it reads: `services.auth.standing`)."""
        try:
            principal = await self.calls.principal(context.invocation_metadata(), Scope.READ)
        except FleetError as exc:
            await context.abort(grpc.StatusCode[exc.grpc_status()], str(exc))
        hub = self.service.replay
        if hub is None:
            await context.abort(grpc.StatusCode.UNAVAILABLE, "this node keeps no replay (FLEET_REPLAY_BYTES=0)")
            return
        watch = GrantWatch(self.auth, principal, GRPC)
        history, queue = hub.subscribe()
        try:
            for kind, raw in history:
                yield read_response(kind, raw)
            while True:
                live = await next_live(queue, watch, context)
                if live is None:
                    await context.abort(
                        grpc.StatusCode.RESOURCE_EXHAUSTED,
                        "this reader fell too far behind the live streams; connect again",
                    )
                    return
                yield read_response(*live)
        finally:
            hub.unsubscribe(queue)


async def next_live(
    queue: asyncio.Queue[Message | None], watch: GrantWatch, context: grpc.aio.ServicerContext
) -> Message | None:
    """A reader's next live message (None: it fell behind), its grant checked while it waits and
    before it is given the message (`watch`)."""
    while True:
        try:
            live = queue.get_nowait()  # a busy reader takes what is queued without a timer
        except asyncio.QueueEmpty:
            try:
                live = await asyncio.wait_for(queue.get(), watch.wait_s())
            except TimeoutError:  # nothing came: time to look at the token again
                await end_if_ended(watch, context)
                continue
        await end_if_ended(watch, context)
        return live


async def end_if_ended(watch: GrantWatch, context: grpc.aio.ServicerContext) -> None:
    """End the call (UNAUTHENTICATED, saying why) if what let it in has ended since."""
    ended = await watch.ended()
    if ended is not None:
        await context.abort(grpc.StatusCode[ended.grpc_status()], str(ended))


async def refuse(context: grpc.aio.ServicerContext, exc: FleetError, relayed_by: str | None = None) -> NoReturn:
    log.warning("stream from %s refused: %s", client_of(context) if relayed_by is None else f"node {relayed_by}", exc)
    if relayed_by is not None:  # the relaying node passes the refusal on with its code
        context.set_trailing_metadata(((ERROR_CODE, exc.code.name),))
    await context.abort(grpc.StatusCode[exc.grpc_status()], str(exc))
    raise AssertionError("not reached: abort raises")


def server_options(max_message_size: int) -> list[tuple[str, int]]:
    """Long-lived streams: keepalive pings both ways, never a limit on client pings."""
    return [
        ("grpc.max_receive_message_length", max_message_size + 1024),
        ("grpc.max_send_message_length", max_message_size + 1024),
        ("grpc.keepalive_time_ms", 10_000),
        ("grpc.keepalive_timeout_ms", 20_000),
        ("grpc.keepalive_permit_without_calls", 1),
        ("grpc.http2.min_recv_ping_interval_without_data_ms", 1_000),
        ("grpc.http2.max_ping_strikes", 0),
        ("grpc.max_connection_idle_ms", 2**31 - 1),
        ("grpc.max_connection_age_ms", 2**31 - 1),
        # Without this the HTTP/2 window grows with how long a fast stream lasts, and memory with it.
        ("grpc.http2.bdp_probe", 0),
    ]


def on_peer_port(context: grpc.aio.ServicerContext) -> bool:
    """The call came to the peer port (TCP), not through the public port's front: that reaches the
    gRPC server on its private Unix socket, or serves the call in process (`WriteCall`, peer "front")."""
    return str(context.peer()).startswith(("ipv4:", "ipv6:"))


def client_of(context: grpc.aio.ServicerContext) -> str:
    """Who is calling, for logs: the client's user-agent (its SDK and version). The peer address is
    the gRPC port's front, so it would say nothing."""
    for key, value in context.invocation_metadata() or ():
        if key == "user-agent":
            return repr(str(value)[:120])
    return "a client without user-agent"


# rerun-sdk 0.22 spoke an earlier version of the protocol (LogMsg of rerun.log_msg.v0), under this
# service. Unanswered, its SDK only reports an HTTP/2 error; answered, the robot is told what to do.
LEGACY_SERVICE_NAME = "rerun.sdk_comms.v0.MessageProxy"
LEGACY_REFUSAL = f"this depot does not speak the gRPC protocol of rerun-sdk 0.22 (rerun.sdk_comms.v0); {UPGRADE_HINT}"


async def refuse_legacy_write(requests: AsyncIterator[bytes], context: grpc.aio.ServicerContext) -> bytes:
    log.warning("stream from %s refused: rerun-sdk 0.22 protocol", client_of(context))
    await context.abort(grpc.StatusCode.FAILED_PRECONDITION, LEGACY_REFUSAL)
    return b""  # not reached: abort raises


async def refuse_legacy_read(request: bytes, context: grpc.aio.ServicerContext) -> AsyncIterator[bytes]:
    await context.abort(grpc.StatusCode.FAILED_PRECONDITION, LEGACY_REFUSAL)
    yield b""  # not reached: abort raises


def add_legacy_refusal(server: grpc.aio.Server) -> None:
    """Answer rerun-sdk 0.22's calls with a clear refusal naming the oldest supported SDK."""
    handlers = {
        "WriteMessages": grpc.stream_unary_rpc_method_handler(refuse_legacy_write),
        "ReadMessages": grpc.unary_stream_rpc_method_handler(refuse_legacy_read),
    }
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(LEGACY_SERVICE_NAME, handlers),))
    server.add_registered_method_handlers(LEGACY_SERVICE_NAME, handlers)


def add_to_server(server: grpc.aio.Server, proxy: MessageProxy) -> None:
    handlers = {
        "WriteMessages": grpc.stream_unary_rpc_method_handler(
            proxy.write_messages,
            request_deserializer=None,  # raw bytes: the inner messages are kept exactly as sent
            response_serializer=sdk_comms_pb2.WriteMessagesResponse.SerializeToString,
        ),
        "ReadMessages": grpc.unary_stream_rpc_method_handler(
            proxy.read_messages,
            request_deserializer=None,
            response_serializer=None,  # responses are built around the stored message bytes
        ),
    }
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE_NAME, handlers),))
    server.add_registered_method_handlers(SERVICE_NAME, handlers)
    add_legacy_refusal(server)


async def _rest_of(context: grpc.aio.ServicerContext) -> AsyncIterator[bytes]:
    """The requests of a call still to come, as they come."""
    while (request := await context.read()) is not grpc.aio.EOF:
        yield request
