"""One way to write a time for a person, used by the CLI and the console alike."""

from __future__ import annotations

import datetime as dt

import pytest

from core import timefmt
from services.cli import output
from services.console import formats


@pytest.mark.parametrize(
    ("kind", "value", "shown"),
    [
        ("timestamp", 1795886824476485321, "2026-11-28T17:27:04.476485321Z"),
        ("timestamp", 0, "1970-01-01T00:00:00.000000000Z"),
        ("duration", 29900000000, "29.9s"),
        ("duration", -1500000000, "-1.5s"),
        ("duration", 3_000_000_000, "3s"),
        ("sequence", 42, "42"),
        (None, 7, "7"),
        ("timestamp", None, "-"),
        ("timestamp", 10**30, str(10**30)),  # out of a calendar's range: as is
    ],
)
def test_timeline_values_by_their_type(kind: str | None, value: int | None, shown: str) -> None:
    assert timefmt.timeline_value(kind, value) == shown


def test_service_times_to_the_second_in_utc() -> None:
    assert timefmt.when("2026-11-23T10:41:05.123456Z") == "2026-11-23 10:41:05 UTC"
    assert timefmt.when("2026-11-23T12:41:05+02:00") == "2026-11-23 10:41:05 UTC"
    assert timefmt.when(dt.datetime(2026, 11, 23, 10, 41, 5, tzinfo=dt.UTC)) == "2026-11-23 10:41:05 UTC"
    assert timefmt.when(None) == timefmt.when("") == "-"
    assert timefmt.when("not a time") == "not a time"


def test_lengths_of_time() -> None:
    assert timefmt.duration(12.5) == "12.5 s"
    assert timefmt.duration(185) == "3 min 05 s"
    assert timefmt.duration(3720) == "1 h 02 min"
    assert timefmt.span("2026-11-23T10:00:00Z", "2026-11-23T10:03:05Z") == "3 min 05 s"
    assert timefmt.span(None, "2026-11-23T10:03:05Z") == "-"


def test_recording_start_time_property_is_a_date() -> None:
    assert timefmt.property_value("RecordingInfo:start_time", 1795886824476485321) == "2026-11-28T17:27:04.476485321Z"
    assert timefmt.property_value("site", "lab-2") == "lab-2"
    assert timefmt.property_value("RecordingInfo:start_time", True) == "True"


def test_the_cli_and_the_console_write_times_alike() -> None:
    """Both front ends use the one formatter: the same value reads the same in each."""
    assert output.timeline_value is timefmt.timeline_value and output.when is timefmt.when
    assert formats.FILTERS["when"] is timefmt.when
    for kind, value in (("timestamp", 1795886824476485321), ("duration", 29900000000), ("sequence", 3)):
        assert formats.timepoint(value, kind) == output.timeline_value(kind, value)
    assert formats.property_field(1795886824476485321, "RecordingInfo:start_time") == output.property_value(
        "RecordingInfo:start_time", 1795886824476485321
    )
