"""Who a call on the gRPC message proxy acts as.

A call that carries `authorization: Bearer TOKEN` metadata (the robot agent, Rerun's clients) is
checked at once. An unmodified SDK sends no metadata at all (DESIGN.md section 3): its stream
proves itself by the `token` field of its `fleet` recording property. Until that token arrives,
what the stream sends is held here, in memory, within a size and a time limit (counted from the
stream's start, silent stretches included), and nothing of it reaches the ingest service; a
stream that sends no valid token in time is refused and leaves nothing behind. What all such
streams of this process hold together is bounded too (`HeldBudget`): FLEET_MAX_STREAMS streams of
FLEET_AUTH_BUFFER_BYTES each would be far more than a node has to spare.

A call another node of the depot relays says so in metadata (`services.cluster.relay`): which node
relays it and whether it is a stream or an upload (an upload is not counted among the streams). That
is believed only from the peer port and, with auth on, with that node's peer token (`relayed`): a
client sending it is refused.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass
from typing import Any

from core.errors import PermissionDeniedError, ResourceExhaustedError, UnauthenticatedError
from services.auth.metadata import GRPC, bearer_token
from services.auth.scopes import Principal, Scope
from services.auth.tokens import FORBIDDEN, INVALID, MISSING, PEER_AUDIENCE, Auth
from services.cluster.relay import INTERNAL_KEYS, PEER_CREDENTIAL, RELAYED_BY, SOURCE_KIND, metadata_value
from services.facts.identity import IDENTITY_PROPERTY, TOKEN_FIELD, FleetClaim, check_robot, fleet_claim
from services.rrd.chunk import chunk_meta
from services.rrd.messages import ArrowMessage, Event, StoreKind

STREAM = "stream"  # the surface of an SDK stream's fleet property token, as refusals are counted
WRITERS = (Scope.INGEST, Scope.WRITE)  # who may stream runs in
Metadata = Iterable[tuple[str, Any]] | None
Decode = Callable[[bytes, int], Event]  # a request's bytes and its offset in the stream -> its message

HOW_TO_SEND = (
    f"log the robot's ingest token as the {TOKEN_FIELD} field of its {IDENTITY_PROPERTY} property first: "
    f'rr.send_property("{IDENTITY_PROPERTY}", rr.AnyValues(robot_id=ROBOT, {TOKEN_FIELD}=TOKEN)) '
    "(an admin creates one with fleet tokens create --scope ingest --robot ROBOT)"
)


@dataclass(frozen=True)
class Relayed:
    """A call another node of the depot passes on."""

    node: str  # the node that relays it (the owner files it and never relays it again)
    live: bool  # a stream (counted among FLEET_MAX_STREAMS here too), not an upload


class HeldBudget:
    """Bytes held by the streams of this process that have not sent their token yet: at most `total`
    together, whatever FLEET_MAX_STREAMS x FLEET_AUTH_BUFFER_BYTES comes to."""

    def __init__(self, total: int) -> None:
        self.total = total
        self.used = 0
        self.peak = 0  # the most held at once since start

    def take(self, nbytes: int) -> bool:
        if self.used + nbytes > self.total:
            return False
        self.used += nbytes
        self.peak = max(self.peak, self.used)
        return True

    def give(self, nbytes: int) -> None:
        self.used -= nbytes


@dataclass
class Admitted:
    """A stream whose fleet property carried a valid token, and what it sent up to that token."""

    principal: Principal
    held: list[Event]  # in the order they came, none given to the ingest service yet
    received: int  # bytes of requests read so far


class CallAuth:
    """Checks the calls of one gRPC message proxy against the depot's tokens."""

    def __init__(self, auth: Auth, *, wait_s: float, buffer_bytes: int, total_bytes: int | None = None) -> None:
        self.auth = auth
        self.wait_s = wait_s  # a stream with no token in its metadata has this long to send one,
        self.buffer_bytes = buffer_bytes  # and may send this much before it,
        self.held = HeldBudget(total_bytes if total_bytes is not None else buffer_bytes)  # and all of them this

    def relayed(self, metadata: Metadata, on_peer_port: bool) -> Relayed | None:
        """Who relays this call, if another node of the depot does; None for a client's call.
        UNAUTHENTICATED if the call says it is relayed but is not from the peer port or, with auth on,
        does not carry the peer token of the node it names: a client could else file uploads outside
        FLEET_MAX_STREAMS, or keep a node from relaying a stream to its run's owner."""
        if all(metadata_value(metadata, key) is None for key in INTERNAL_KEYS):
            return None
        node = metadata_value(metadata, RELAYED_BY)
        if not on_peer_port or node is None or not self._peer_token_of(node, metadata_value(metadata, PEER_CREDENTIAL)):
            self.auth.refused(GRPC, INVALID)
            raise UnauthenticatedError(
                f"the metadata {', '.join(INTERNAL_KEYS)} is for the depot's own nodes, on their peer port, "
                "with a node's credential: a client may not send it",
                INVALID,
            )
        return Relayed(node, metadata_value(metadata, SOURCE_KIND) != "upload")

    def _peer_token_of(self, node: str, token: str | None) -> bool:
        """With auth on, `token` is a peer token of `node` signed with the depot's key. With auth off
        nothing is checked (FLEET_AUTH=off binds loopback only: whoever reaches the ports is trusted)."""
        if not self.auth.enabled:
            return True
        if not token:
            return False
        try:
            claims = self.auth.claims(token)  # a signature and an expiry: no catalog, no I/O
        except UnauthenticatedError:
            return False
        return claims.get("aud") == PEER_AUDIENCE and claims.get("sub") == f"node:{node}"

    def needs_property_token(self, metadata: Metadata) -> bool:
        """Auth is on and the call carries no token of its own: its fleet property must."""
        return self.auth.enabled and bearer_token(metadata) is None

    async def principal(self, metadata: Metadata, *scopes: Scope) -> Principal:
        """Who the call's `authorization` metadata stands for, holding one of `scopes`:
        UNAUTHENTICATED without a valid token (auth on), PERMISSION_DENIED without the scope."""
        token = bearer_token(metadata)
        if not self.auth.enabled:
            return self.auth.authenticate(token, GRPC)  # the local principal: nothing to look up
        principal = await asyncio.to_thread(self.auth.authenticate, token, GRPC)  # may ask the catalog
        return self.auth.authorize(principal, GRPC, *scopes)

    async def await_property_token(self, requests: AsyncIterator[bytes], decode: Decode) -> Admitted:
        """Read the stream up to the message carrying its fleet property's token, holding every
        message before it; the token's principal if it may stream runs in. UNAUTHENTICATED if the
        stream ends, runs past the time or size limit, or sends an invalid token; PERMISSION_DENIED
        if the token holds neither ingest nor write."""
        admitted = Admitted(Principal("", frozenset()), [], 0)  # what it holds so far
        try:
            return await self._read_to_token(requests, decode, admitted)
        finally:  # admitted (what it held now goes to the ingest service) or refused: none held now
            self.held.give(admitted.received)

    async def _read_to_token(self, requests: AsyncIterator[bytes], decode: Decode, admitted: Admitted) -> Admitted:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.wait_s
        while True:
            try:
                request = await asyncio.wait_for(anext(requests), deadline - loop.time())
            except TimeoutError:
                raise self._no_token(f"no token came within {self.wait_s:g} s of the stream's start") from None
            except StopAsyncIteration:
                raise self._no_token("the stream ended before any token") from None
            if admitted.received + len(request) > self.buffer_bytes:
                raise self._no_token(f"more than {self.buffer_bytes} bytes came before any token")
            if not self.held.take(len(request)):
                raise ResourceExhaustedError(
                    f"streams waiting for their token already hold {self.held.used} bytes on this node, "
                    "its limit (FLEET_AUTH_BUFFER_TOTAL_BYTES): retry later, or send the token as "
                    "`authorization: Bearer TOKEN` metadata"
                )
            event = decode(request, admitted.received)
            admitted.received += len(request)
            admitted.held.append(event)
            if isinstance(event, ArrowMessage) and (claim := _claim_of(event)) is not None:
                principal = await asyncio.to_thread(self.auth.authenticate, claim.token, STREAM)
                self.auth.authorize(principal, STREAM, *WRITERS)
                self._check_robot(principal, claim, event.store_id.recording_id)
                admitted.principal = principal
                return admitted

    def _check_robot(self, principal: Principal, claim: FleetClaim, run_id: str) -> None:
        """Checked here, before anything is filed: what the SDK sends before its fleet property (the
        same batch may hold data first) would else be filed before the ingest service sees the robot
        the property names."""
        if claim.robot is None:
            return
        try:
            check_robot(principal.robot, run_id, claim.robot)
        except PermissionDeniedError:
            self.auth.refused(STREAM, FORBIDDEN)
            raise

    def _no_token(self, what: str) -> UnauthenticatedError:
        self.auth.refused(STREAM, MISSING)
        return UnauthenticatedError(
            f"this depot takes streams from robots with a token: {what}, and nothing of it was kept; "
            f"{HOW_TO_SEND}, or send `authorization: Bearer TOKEN` metadata",
            MISSING,
        )


def _claim_of(msg: ArrowMessage) -> FleetClaim | None:
    """The token (and robot) of a recording's fleet property chunk; None for any other chunk."""
    if msg.store_id.kind != StoreKind.RECORDING:
        return None
    return fleet_claim(msg, chunk_meta(msg))
