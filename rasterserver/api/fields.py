"""Types of the API's fields and parameters that carry a rule: times, dates and enumerations.

They validate with the same rules as the command line (:mod:`rasterserver.times`) and are
published in the OpenAPI document: times as ``date-time``, dates as ``date``, enumerations
with their values.

* :data:`Instant`: ISO 8601 text with a zone, or a date alone (00:00 UTC). A time without
  zone and a number are refused (422); pydantic would otherwise read ``0.5`` as seconds since
  1970 and take a time without zone as UTC.
* :data:`Day`: ``YYYY-MM-DD`` text only (``0`` is not 1970-01-01).
* :data:`Sex`, :data:`Role`, :data:`AccountKind`, :data:`AcquisitionKind`, :data:`FrameRole`:
  the values the catalogue allows (its check constraints), as ``enum`` in the schema.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BeforeValidator

from rasterserver.errors import InputError
from rasterserver.times import parse_day, parse_instant, require_zone

__all__ = ["AccountKind", "AcquisitionKind", "Day", "FrameRole", "Instant", "Role", "Sex"]

T = TypeVar("T")


def _as_value_error(parse: Callable[[Any], T]) -> Callable[[Any], T]:
    """``parse`` with its :class:`InputError` turned into the ``ValueError`` pydantic reports
    as a 422 naming the field."""

    def validate(value: Any) -> T:
        try:
            return parse(value)
        except InputError as exc:
            raise ValueError(str(exc)) from None

    return validate


def _instant(value: Any) -> dt.datetime:
    if isinstance(value, dt.datetime):  # from Python, not from a request
        return require_zone(value, "time")
    return parse_instant(value, "time")


def _day(value: Any) -> dt.date:
    if isinstance(value, dt.date) and not isinstance(value, dt.datetime):
        return value
    return parse_day(value, "date")


#: A time: ISO 8601 with its zone, or a date alone meaning 00:00 UTC.
Instant = Annotated[dt.datetime, BeforeValidator(_as_value_error(_instant))]
#: A calendar date, ``YYYY-MM-DD``.
Day = Annotated[dt.date, BeforeValidator(_as_value_error(_day))]

# The values of the catalogue's check constraints (rasterserver.catalog.models and
# auth_models); tests/api/test_fields.py checks that they agree.
Sex = Literal["female", "male", "other", "unknown"]
Role = Literal["admin", "clinician", "station", "researcher"]
AccountKind = Literal["user", "service"]
AcquisitionKind = Literal["patient", "calibration", "test"]
FrameRole = Literal["raster", "projector-off", "projector-on", "dark", "other"]
