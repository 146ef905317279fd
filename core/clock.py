"""The clock, and how times are written: aware UTC datetimes everywhere, ISO-8601 with a Z outside."""

from __future__ import annotations

import datetime as dt


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def aware(value: dt.datetime) -> dt.datetime:
    """A time read from the catalog, in UTC (DuckDB hands timestamps back without a zone; they are
    stored in UTC)."""
    return value if value.tzinfo is not None else value.replace(tzinfo=dt.UTC)


def iso_utc(value: dt.datetime | None) -> str | None:
    """ISO-8601 in UTC with a Z, as every answer writes times."""
    return aware(value).isoformat().replace("+00:00", "Z") if value is not None else None
