"""The catalogue's one timestamp type: stored in UTC, read back in UTC, on every backend.

``DateTime(timezone=True)`` alone is not enough. PostgreSQL's ``timestamptz`` converts an
aware time to UTC, but SQLite has no time zones: SQLAlchemy writes the clock time and drops
the offset, so ``10:15+05:00`` was stored, and read back, as ``10:15`` UTC (five hours
wrong), and a filter bound the same way compared the wrong instants. Read back, SQLite gave
times without a zone and PostgreSQL gave them in the session's zone.

:class:`UtcDateTime` converts every aware time to UTC before it is bound (rows, filters, and
the driver-level inserts that use the type's bind processor), and returns every time as an
aware UTC datetime. The stored form does not change (SQLite's ISO text, PostgreSQL's
``timestamptz``), so no migration is needed and stored times written in UTC read the same.

A time without a zone is refused (:class:`NaiveDatetimeError`): SQLite would take it as UTC
and PostgreSQL as the server's local time, so its meaning would depend on the backend. User
input is checked before it gets here (:mod:`rasterserver.times`); reaching this check is a
programming error.
"""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import DateTime
from sqlalchemy.engine import Dialect
from sqlalchemy.types import TypeDecorator

__all__ = ["NaiveDatetimeError", "UtcDateTime"]


class NaiveDatetimeError(ValueError):
    """A datetime without a time zone was about to be stored or compared."""


class UtcDateTime(TypeDecorator[dt.datetime]):
    """A timestamp column (``DateTime(timezone=True)``) that holds instants in UTC."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value: Any, dialect: Dialect) -> Any:
        """Convert an aware datetime to UTC; refuse a naive one."""
        if value is None or not isinstance(value, dt.datetime):
            # None, or a SQL expression's value that is not ours to judge (a date, say)
            return value
        if value.tzinfo is None or value.utcoffset() is None:
            raise NaiveDatetimeError(
                f"a catalogue time must carry its time zone, got {value.isoformat()}"
            )
        return value.astimezone(dt.UTC)

    def process_result_value(self, value: Any, dialect: Dialect) -> dt.datetime | None:
        """Return the stored time as an aware UTC datetime (SQLite stores UTC without zone)."""
        if value is None:
            return None
        if value.tzinfo is None:
            return value.replace(tzinfo=dt.UTC)
        return value.astimezone(dt.UTC)

    def result_processor(self, dialect: Dialect, coltype: object) -> Any:
        """On SQLite, parse the stored text straight into an aware datetime.

        Lists of a hundred acquisitions read a hundred times: parsing ``text + "+00:00"``
        costs a tenth of parsing and then ``replace(tzinfo=...)`` (keyword arguments are
        slow), so the UTC type reads faster than the plain one plus a conversion did. Text
        in any other form goes the general way.
        """
        general = super().result_processor(dialect, coltype)
        if dialect.name != "sqlite" or general is None:
            return general
        parse = dt.datetime.fromisoformat

        def process(value: Any) -> dt.datetime | None:
            if value is None:
                return None
            try:
                parsed = parse(value + "+00:00")
            except (TypeError, ValueError):
                return general(value)
            return parsed if parsed.tzinfo is not None else general(value)

        return process
