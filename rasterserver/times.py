"""Dates and times typed by users (CLI options, HTTP fields and queries): one set of rules.

* A **time** is ISO 8601 with its zone: ``2025-03-01T10:15+01:00`` or ``2025-03-01T09:15Z``.
  It keeps its offset here (an acquisition's visit is the day at that offset, the clinic's
  day); the catalogue stores every time in UTC.
* A **date alone** (``2025-03-01``) where a time is expected means 00:00 UTC of that day
  (``--since 2025-03-01``).
* A time **without a zone** (``2025-03-01T10:15``) is refused. Taken as UTC it would be hours
  wrong at every clinic that is not on UTC, silently (the defect this replaced lost offsets
  in just that way); taken as the server's local time it would depend on where the server
  runs. FHIR, which clinical systems exchange, makes the same rule: a dateTime with a time
  SHALL carry its zone.
* Numbers are not dates: ``0`` or ``0.5`` are refused, not read as seconds since 1970.

A **date** (a birth date, a visit date) is ``YYYY-MM-DD``.
"""

from __future__ import annotations

import datetime as dt

from rasterserver.errors import InputError

__all__ = ["TIME_RULE", "parse_day", "parse_instant", "require_zone"]

#: The rule in one line, for option help and error messages.
TIME_RULE = (
    "ISO 8601 with its zone, e.g. 2025-03-01T10:15+01:00 or 2025-03-01T09:15Z; "
    "a date alone is 00:00 UTC"
)


def require_zone(value: dt.datetime, what: str) -> dt.datetime:
    """Return ``value`` if it carries its time zone and can be stored.

    Parameters
    ----------
    value : datetime.datetime
        A time with its zone.
    what : str
        What the value is, for the message (an option or field name).

    Returns
    -------
    datetime.datetime
        ``value`` itself.

    Raises
    ------
    InputError
        ``value`` has no zone, or it falls outside the years 1 to 9999 in UTC.
    """
    if value.tzinfo is None or value.utcoffset() is None:
        raise InputError(
            f"{what}: {value.isoformat()} has no time zone: add Z for UTC or "
            "the offset, e.g. +01:00"
        )
    try:
        value.astimezone(dt.UTC)  # how the catalogue will store it
    except OverflowError:
        raise InputError(f"{what}: {value.isoformat()} is out of range") from None
    return value


def parse_instant(text: str, what: str) -> dt.datetime:
    """Parse a user's time (see the module's rules).

    Parameters
    ----------
    text : str
        ISO 8601 time with its zone, or a date alone (00:00 UTC of that day).
    what : str
        What the value is, for the message.

    Returns
    -------
    datetime.datetime
        An aware datetime, with the offset given (UTC for a date alone).

    Raises
    ------
    InputError
        Not ISO 8601, a time without zone, or out of range.
    """
    if not isinstance(text, str):
        raise InputError(f"{what}: expected a date or time as text ({TIME_RULE})")
    try:
        day = dt.date.fromisoformat(text)
    except ValueError:
        pass
    else:
        return dt.datetime.combine(day, dt.time(), tzinfo=dt.UTC)
    try:
        value = dt.datetime.fromisoformat(text)
    except ValueError:
        raise InputError(f"{what}: {text!r} is not a date or time ({TIME_RULE})") from None
    if value.tzinfo is None:
        raise InputError(
            f"{what}: {text!r} has no time zone: add Z for UTC or the offset, e.g. {text}+01:00"
        )
    return require_zone(value, what)


def parse_day(text: str, what: str) -> dt.date:
    """Parse a user's date, ``YYYY-MM-DD``.

    Raises
    ------
    InputError
        Anything else, numbers and times included.
    """
    if not isinstance(text, str):
        raise InputError(f"{what}: expected a date as text (YYYY-MM-DD)")
    try:
        return dt.date.fromisoformat(text)
    except ValueError:
        raise InputError(f"{what}: {text!r} is not a date (YYYY-MM-DD)") from None
