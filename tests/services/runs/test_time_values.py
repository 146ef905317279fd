import pytest

from core.errors import BadParameterError
from services.runs.download import parse_time_value


@pytest.mark.parametrize(
    ("kind", "text", "value"),
    [
        ("sequence", "42", 42),
        ("sequence", "-3", -3),
        ("duration", "12.5s", 12_500_000_000),
        ("duration", "250ms", 250_000_000),
        ("duration", "1.000000001s", 1_000_000_001),
        ("duration", "3us", 3_000),
        ("duration", "2m", 120_000_000_000),
        ("duration", "-0.5s", -500_000_000),
        ("duration", "77", 77),
        ("timestamp", "2026-11-21T08:00:00Z", 1_795_248_000_000_000_000),
        ("timestamp", "2026-11-21T08:00:00.123456789Z", 1_795_248_000_123_456_789),
        ("timestamp", "2026-11-21T09:00:00+01:00", 1_795_248_000_000_000_000),
        ("timestamp", "2026-11-21", 1_795_219_200_000_000_000),
        ("timestamp", "1795248000000000000", 1_795_248_000_000_000_000),
        # int64's bounds, and the latest timestamp it holds, are accepted
        ("sequence", "9223372036854775807", 2**63 - 1),
        ("sequence", "-9223372036854775808", -(2**63)),
        ("timestamp", "2262-04-11T23:47:16Z", 9_223_372_036_000_000_000),
    ],
)
def test_values_by_timeline_type(kind: str, text: str, value: int):
    assert parse_time_value("start", kind, text) == value


@pytest.mark.parametrize(
    ("kind", "text", "says"),
    [
        ("sequence", "1.5", "use "),
        ("duration", "12 s", "use "),
        ("duration", "5 days", "use "),
        ("timestamp", "yesterday", "use "),
        ("timestamp", "2026-13-40", "use "),
        # outside int64
        ("sequence", "-99999999999999999999", "outside the range"),
        ("sequence", "9223372036854775808", "outside the range"),
        ("sequence", "-9223372036854775809", "outside the range"),
        ("timestamp", "2263-01-01T00:00:00Z", "outside the range"),
        ("timestamp", "2262-04-12", "outside the range"),
        ("timestamp", "1677-09-20", "outside the range"),
        ("timestamp", "99999999999999999999", "outside the range"),
        ("duration", "9999999999h", "outside the range"),
        ("duration", "-2562048h", "outside the range"),
    ],
)
def test_refused_values_say_why(kind: str, text: str, says: str):
    with pytest.raises(BadParameterError) as info:
        parse_time_value("start", kind, text)
    assert info.value.parameter == "start" and says in str(info.value)
