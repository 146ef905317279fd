"""The token a gRPC call carries: `authorization: Bearer TOKEN` metadata, as Rerun's clients and
the robot agent send it."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


def bearer_token(metadata: Iterable[tuple[str, Any]] | None) -> str | None:
    """The token of a call's metadata; None if it has no `authorization` entry; "" if that entry is
    not a bearer token (refused as such)."""
    for key, value in metadata or ():
        if key == "authorization":
            text = value.decode() if isinstance(value, bytes) else str(value)
            scheme, _, token = text.strip().partition(" ")
            return token.strip() if scheme.lower() == "bearer" else ""
    return None
