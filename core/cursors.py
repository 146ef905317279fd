"""The cursor of a page of rows ordered by (created_at, id): opaque to clients (base64 of the last
row's time and id), and checked when it comes back, so a tampered one is a 422, never a query error."""

from __future__ import annotations

import base64
import datetime as dt
import json

from core.clock import iso_utc
from core.errors import BadParameterError
from core.text import storable

MAX_CURSOR_LENGTH = 512  # a cursor this depot gives out is a few dozen characters


def encode_cursor(created_at: dt.datetime, ident: str) -> str:
    raw = json.dumps([iso_utc(created_at), ident])
    return base64.urlsafe_b64encode(raw.encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[dt.datetime, str]:
    """The (created_at, id) a cursor carries."""
    bad = BadParameterError("cursor", "not a cursor this service gave out: pass `next_cursor` as is")
    if len(cursor) > MAX_CURSOR_LENGTH:
        raise bad
    try:
        created, ident = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
        when = dt.datetime.fromisoformat(created.replace("Z", "+00:00"))
    except (ValueError, TypeError, AttributeError, RecursionError):  # binascii.Error is a ValueError
        raise bad from None
    if not isinstance(ident, str) or not storable(ident) or when.tzinfo is None:
        raise bad
    return when, ident
