"""A page cursor comes back as it was given out, and anything else is one 422 naming the cursor."""

from __future__ import annotations

import base64
import datetime as dt

import pytest

from core.cursors import MAX_CURSOR_LENGTH, decode_cursor, encode_cursor
from core.errors import BadParameterError


def _b64(text: str) -> str:
    return base64.urlsafe_b64encode(text.encode()).decode().rstrip("=")


def test_a_cursor_comes_back_as_it_was_given_out():
    when = dt.datetime(2026, 11, 29, 9, 30, 1, 123456, tzinfo=dt.UTC)
    assert decode_cursor(encode_cursor(when, "ev-0123456789abcdef")) == (when, "ev-0123456789abcdef")


@pytest.mark.parametrize(
    "cursor",
    [
        "",
        "not base64 at all!",
        _b64("[]"),
        _b64('["2026-11-29T09:30:00Z"]'),
        _b64('["2026-11-29T09:30:00", "naive-time"]'),
        _b64('["yesterday", "x"]'),
        _b64('["2026-11-29T09:30:00Z", 7]'),
        _b64('["2026-11-29T09:30:00Z", "nul\\u0000"]'),
        _b64('["2026-11-29T09:30:00Z", "\\ud800"]'),
        _b64("[" * 5000),
        "A" * (MAX_CURSOR_LENGTH + 1),
    ],
)
def test_a_cursor_not_given_out_is_refused_naming_the_cursor(cursor: str):
    with pytest.raises(BadParameterError, match="next_cursor"):
        decode_cursor(cursor)
