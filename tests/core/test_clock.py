import datetime as dt

import pytest

from core.clock import parse_duration
from core.errors import InvalidArgumentError


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("90d", dt.timedelta(days=90)),
        ("12h", dt.timedelta(hours=12)),
        ("30m", dt.timedelta(minutes=30)),
        ("45s", dt.timedelta(seconds=45)),
        ("2w", dt.timedelta(weeks=2)),
        ("1h30m", dt.timedelta(hours=1, minutes=30)),
        ("1.5h", dt.timedelta(minutes=90)),
        (" 7D ", dt.timedelta(days=7)),
    ],
)
def test_parse_duration_reads_what_people_type(text: str, expected: dt.timedelta):
    assert parse_duration(text) == expected


@pytest.mark.parametrize("text", ["", "90", "d", "3x", "1 h", "-5m", "1h-", "forever", "1e3s"])
def test_parse_duration_names_the_form_it_wants(text: str):
    with pytest.raises(InvalidArgumentError) as caught:
        parse_duration(text)
    message = str(caught.value)
    assert repr(text) in message and "90d, 12h, 30m, 45s or 2w" in message and "\n" not in message


@pytest.mark.parametrize("text", ["0s", "0d0h"])
def test_parse_duration_refuses_no_time_at_all(text: str):
    with pytest.raises(InvalidArgumentError, match="longer than zero"):
        parse_duration(text)


def test_parse_duration_refuses_more_than_a_clock_counts():
    with pytest.raises(InvalidArgumentError, match="shorter duration"):
        parse_duration("9" * 30 + "w")
