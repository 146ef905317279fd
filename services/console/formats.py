"""How the console writes numbers, sizes and times (template filters); times as the CLI writes
them (core.timefmt)."""

from __future__ import annotations

from typing import Any

from core.timefmt import duration, property_value, span, timeline_value, when

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


def timepoint(value: Any, timeline_type: str | None) -> str:
    """`{{ value|timepoint(type) }}`: a value on a timeline of that type (core.timefmt)."""
    return timeline_value(timeline_type, value)


def property_field(value: Any, field: str) -> str:
    """`{{ value|property_field(field) }}`: a recording property's value (start_time as a date)."""
    return property_value(field, value)


FILTERS = {
    "size": size,
    "count": count,
    "when": when,
    "duration": duration,
    "span": span,
    "timepoint": timepoint,
    "property_field": property_field,
}
