"""How the console writes numbers, sizes and times (template filters)."""

from __future__ import annotations

import datetime as dt
from typing import Any

_UNITS = ("B", "KB", "MB", "GB", "TB", "PB")


def size(value: Any) -> str:
    """Bytes as people read them: 1.5 MB (powers of 1000, as disks are sold)."""
    if value is None:
        return "-"
    amount = float(value)
    for unit in _UNITS:
        if abs(amount) < 1000 or unit == _UNITS[-1]:
            return f"{amount:.0f} {unit}" if unit == "B" else f"{amount:.1f} {unit}"
        amount /= 1000
    return f"{amount:.1f} {_UNITS[-1]}"


def count(value: Any) -> str:
    """A count with thousands separators."""
    return "-" if value is None else f"{int(value):,}"


def when(value: Any) -> str:
    """An ISO-8601 time (or datetime) as `2026-11-23 10:41:05 UTC`; as given if it does not parse."""
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


def duration(seconds: Any) -> str:
    """Seconds as `1 h 02 min`, `3 min 05 s` or `12.5 s`."""
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
    """The length of a run from its ISO-8601 start and end."""
    if not start or not end:
        return "-"
    try:
        a = dt.datetime.fromisoformat(str(start).replace("Z", "+00:00"))
        b = dt.datetime.fromisoformat(str(end).replace("Z", "+00:00"))
    except ValueError:
        return "-"
    return duration((b - a).total_seconds())


FILTERS = {"size": size, "count": count, "when": when, "duration": duration, "span": span}
