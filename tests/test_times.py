"""Users' dates and times: ISO 8601 with a zone, a date alone as 00:00 UTC, nothing guessed."""

from __future__ import annotations

import datetime as dt

import pytest

from rasterserver.errors import InputError
from rasterserver.times import parse_day, parse_instant, require_zone

UTC = dt.UTC


@pytest.mark.parametrize(
    ("text", "instant"),
    [
        ("2025-03-01T10:15+05:00", dt.datetime(2025, 3, 1, 5, 15, tzinfo=UTC)),
        ("2025-03-01T10:15:30.5-03:30", dt.datetime(2025, 3, 1, 13, 45, 30, 500000, tzinfo=UTC)),
        ("2025-03-01T10:15Z", dt.datetime(2025, 3, 1, 10, 15, tzinfo=UTC)),
        ("2025-03-01 10:15+00:00", dt.datetime(2025, 3, 1, 10, 15, tzinfo=UTC)),
        ("2025-03-01", dt.datetime(2025, 3, 1, tzinfo=UTC)),
    ],
)
def test_times_with_a_zone_keep_their_instant(text: str, instant: dt.datetime) -> None:
    parsed = parse_instant(text, "--since")
    assert parsed == instant and parsed.utcoffset() is not None


def test_the_offset_given_is_kept_for_the_local_day() -> None:
    parsed = parse_instant("2025-03-02T01:00+05:00", "--acquired-at")
    assert parsed.date() == dt.date(2025, 3, 2)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("2025-03-01T10:15", "no time zone"),
        ("2025-03-01T10:15:00.000", "no time zone"),
        ("0", "not a date or time"),
        ("0.5", "not a date or time"),
        ("1740822900", "not a date or time"),
        ("", "not a date or time"),
        (" 2025-03-01", "not a date or time"),
        ("yesterday", "not a date or time"),
        ("2025-02-30", "not a date or time"),
        ("0001-01-01T00:00+05:00", "out of range"),
        ("9999-12-31T23:59-05:00", "out of range"),
        (0.5, "as text"),
        (0, "as text"),
    ],
)
def test_what_is_not_an_unambiguous_time_is_refused(value: object, message: str) -> None:
    with pytest.raises(InputError, match=message) as caught:
        parse_instant(value, "--until")  # type: ignore[arg-type]
    assert str(caught.value).startswith("--until: ")


def test_require_zone() -> None:
    aware = dt.datetime(2025, 3, 1, 10, tzinfo=dt.timezone(dt.timedelta(hours=1)))
    assert require_zone(aware, "t") is aware
    with pytest.raises(InputError, match="no time zone"):
        require_zone(dt.datetime(2025, 3, 1, 10), "t")


@pytest.mark.parametrize("value", ["0", "0.5", "2011-05-02T00:00Z", "02.05.2011", "", 0, 0.5])
def test_a_date_is_yyyy_mm_dd_only(value: object) -> None:
    assert parse_day("2011-05-02", "--birth-date") == dt.date(2011, 5, 2)
    with pytest.raises(InputError, match="--birth-date"):
        parse_day(value, "--birth-date")  # type: ignore[arg-type]
