"""The clock, and how times are written: aware UTC datetimes everywhere, ISO-8601 with a Z outside."""

from __future__ import annotations

import datetime as dt
import re

from core.errors import InvalidArgumentError


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def aware(value: dt.datetime) -> dt.datetime:
    """A time read from the catalog, in UTC (DuckDB hands timestamps back without a zone; they are
    stored in UTC)."""
    return value if value.tzinfo is not None else value.replace(tzinfo=dt.UTC)


def iso_utc(value: dt.datetime | None) -> str | None:
    """ISO-8601 in UTC with a Z, as every answer writes times."""
    return aware(value).isoformat().replace("+00:00", "Z") if value is not None else None


_DURATION_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 7 * 86400}
_DURATION_PART = re.compile(r"(\d+(?:\.\d+)?)([smhdw])")


def parse_duration(text: str) -> dt.timedelta:
    """A lifetime as people type it: a number and a unit (s, m, h, d, w), like 90d, 12h, 30m, 45s
    or 2w, or several together (1h30m). One clear error for anything else, or for zero."""
    spoken = text.strip().lower()
    if not spoken or _DURATION_PART.sub("", spoken):
        raise InvalidArgumentError(
            f"{text!r} is not a duration: a number and a unit (s, m, h, d, w), like 90d, 12h, 30m, 45s or 2w"
        )
    seconds = sum(float(n) * _DURATION_UNITS[unit] for n, unit in _DURATION_PART.findall(spoken))
    if seconds <= 0:
        raise InvalidArgumentError(f"{text!r} is no time at all: give a duration longer than zero, like 1h")
    try:
        return dt.timedelta(seconds=seconds)
    except OverflowError:
        raise InvalidArgumentError(f"{text!r} is longer than any clock counts: give a shorter duration") from None
