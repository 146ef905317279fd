"""The token a gRPC call carries: `authorization: Bearer TOKEN` metadata, as Rerun's clients and
the robot agent send it."""

from __future__ import annotations

import asyncio
from collections.abc import Iterable
from typing import Any

from services.auth.scopes import Principal, Scope
from services.auth.tokens import Auth

GRPC = "grpc"  # the surface gRPC calls' refusals are counted under in /metrics


def bearer_token(metadata: Iterable[tuple[str, Any]] | None) -> str | None:
    """The token of a call's metadata; None if it has no `authorization` entry; "" if that entry is
    not a bearer token (refused as such)."""
    for key, value in metadata or ():
        if key == "authorization":
            text = value.decode() if isinstance(value, bytes) else str(value)
            scheme, _, token = text.strip().partition(" ")
            return token.strip() if scheme.lower() == "bearer" else ""
    return None


async def call_principal(auth: Auth, metadata: Iterable[tuple[str, Any]] | None, *scopes: Scope) -> Principal:
    """Who a gRPC call's `authorization` metadata stands for, holding one of `scopes`:
    UNAUTHENTICATED without a valid token (auth on), PERMISSION_DENIED without the scope. Checked
    off the event loop (it may ask the catalog)."""
    token = bearer_token(metadata)
    if not auth.enabled:
        return auth.authenticate(token, GRPC)  # the local principal: nothing to look up
    principal = await asyncio.to_thread(auth.authenticate, token, GRPC)
    return auth.authorize(principal, GRPC, *scopes)
