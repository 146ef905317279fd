"""Who a call on the gRPC message proxy acts as.

A call that carries `authorization: Bearer TOKEN` metadata (the robot agent, Rerun's clients) is
checked at once. An unmodified SDK sends no metadata at all (DESIGN.md section 3): its stream
proves itself by the `token` field of its `fleet` recording property. Until that token arrives,
what the stream sends is held here, in memory, within a size and a time limit (counted from the
stream's start, silent stretches included), and nothing of it reaches the ingest service; a
stream that sends no valid token in time is refused and leaves nothing behind.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass
from typing import Any

from core.errors import PermissionDeniedError, UnauthenticatedError
from services.auth.metadata import GRPC, bearer_token
from services.auth.scopes import Principal, Scope
from services.auth.tokens import FORBIDDEN, MISSING, Auth
from services.ingest.identity import IDENTITY_PROPERTY, TOKEN_FIELD, FleetClaim, check_robot, fleet_claim
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


@dataclass
class Admitted:
    """A stream whose fleet property carried a valid token, and what it sent up to that token."""

    principal: Principal
    held: list[Event]  # in the order they came, none given to the ingest service yet
    received: int  # bytes of requests read so far


class CallAuth:
    """Checks the calls of one gRPC message proxy against the depot's tokens."""

    def __init__(self, auth: Auth, *, wait_s: float, buffer_bytes: int) -> None:
        self.auth = auth
        self.wait_s = wait_s  # a stream with no token in its metadata has this long to send one,
        self.buffer_bytes = buffer_bytes  # and may send this much before it

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
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.wait_s
        held: list[Event] = []
        received = 0
        while True:
            try:
                request = await asyncio.wait_for(anext(requests), deadline - loop.time())
            except TimeoutError:
                raise self._no_token(f"no token came within {self.wait_s:g} s of the stream's start") from None
            except StopAsyncIteration:
                raise self._no_token("the stream ended before any token") from None
            if received + len(request) > self.buffer_bytes:
                raise self._no_token(f"more than {self.buffer_bytes} bytes came before any token")
            event = decode(request, received)
            received += len(request)
            held.append(event)
            if isinstance(event, ArrowMessage) and (claim := _claim_of(event)) is not None:
                principal = await asyncio.to_thread(self.auth.authenticate, claim.token, STREAM)
                self.auth.authorize(principal, STREAM, *WRITERS)
                self._check_robot(principal, claim, event.store_id.recording_id)
                return Admitted(principal, held, received)

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
