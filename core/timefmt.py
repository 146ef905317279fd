"""How a time is written for a person to read, the same in the CLI and the console: service times
(ISO-8601) as `2026-11-23 10:41:05 UTC`, timeline values by their timeline's type (timestamps as
dates to the nanosecond, durations as `29.9s`, sequences as numbers: the forms `fleet view
--start/--end` accepts), and lengths of time as `3 min 05 s`."""

from __future__ import annotations

import datetime as dt
from typing import Any

NS = 1_000_000_000
TIMESTAMP_PROPERTIES = frozenset({"RecordingInfo:start_time"})  # property fields holding epoch nanoseconds


def when(value: Any) -> str:
    """An ISO-8601 time (or datetime) to the second in UTC; "-" for none; as given if it does not parse."""
    if value is None or value == "":
        return "-"
    if isinstance(value, dt.datetime):
        moment = value
    else:
        try:
            moment = dt.datetime.fromisoformat(str(value).replace("Z", "+00:00"))
        except ValueError:
            return str(value)
    if moment.tzinfo is not None:
        moment = moment.astimezone(dt.UTC)
    return moment.strftime("%Y-%m-%d %H:%M:%S") + " UTC"


def timeline_value(timeline_type: str | None, value: Any) -> str:
    """A value on a timeline of `timeline_type` (timestamp, duration, sequence); "-" for none."""
    if value is None or value == "":
        return "-"
    try:
        number = int(value)
    except (TypeError, ValueError):
        return str(value)
    if timeline_type == "timestamp":
        return timestamp(number)
    if timeline_type == "duration":
        sign = "-" if number < 0 else ""
        seconds, nanos = divmod(abs(number), NS)
        return f"{sign}{seconds}.{nanos:09d}".rstrip("0").rstrip(".") + "s"
    return str(number)


def timestamp(ns: int) -> str:
    """Epoch nanoseconds as ISO-8601 UTC with the nanoseconds kept (trailing zeros too: aligned)."""
    seconds, nanos = divmod(ns, NS)
    try:
        stamp = dt.datetime.fromtimestamp(seconds, dt.UTC).strftime("%Y-%m-%dT%H:%M:%S")
    except (OverflowError, OSError, ValueError):
        return str(ns)
    return f"{stamp}.{nanos:09d}Z"


def property_value(field: str, value: Any) -> str:
    """A recording property's value: the timestamps among them (RecordingInfo:start_time) as dates."""
    if field in TIMESTAMP_PROPERTIES and isinstance(value, int) and not isinstance(value, bool):
        return timestamp(value)
    return str(value)


def duration(seconds: Any) -> str:
    """A length of time in seconds as `1 h 02 min`, `3 min 05 s` or `12.5 s`."""
    if seconds is None:
        return "-"
    total = float(seconds)
    if total < 60:
        return f"{total:.1f} s"
    minutes, secs = divmod(int(total), 60)
    hours, minutes = divmod(minutes, 60)
    if hours:
        return f"{hours} h {minutes:02d} min"
    return f"{minutes} min {secs:02d} s"


def span(start: Any, end: Any) -> str:
    """The time between two ISO-8601 times, as `duration` writes it."""
    if not start or not end:
        return "-"
    try:
        a = dt.datetime.fromisoformat(str(start).replace("Z", "+00:00"))
        b = dt.datetime.fromisoformat(str(end).replace("Z", "+00:00"))
    except ValueError:
        return "-"
    return duration((b - a).total_seconds())
