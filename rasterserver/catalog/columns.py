"""Light SQLAlchemy Core views of the tables the catalogue's readers query.

The ORM models (:mod:`rasterserver.catalog.models`) are the schema; building their classes
costs about 0.1 s at every start, which ``rasterserver list`` would spend for one SELECT.
These views name only the columns the listing statements read
(:mod:`rasterserver.catalog.listing`, :func:`rasterserver.catalog.lookup.patient_id_of`),
with the types that decode their values (times as aware UTC datetimes, dates as dates). The
SQL they give is the same as the models'; a test checks every column here against them.
"""

from __future__ import annotations

from sqlalchemy import Date, Integer, String, Text, column, table

from rasterserver.catalog.utc_datetime import UtcDateTime

__all__ = ["acquisition", "frame", "patient"]

patient = table(
    "patient",
    column("id", Integer),
    column("identifier", String),
    column("identifier_key", String),
    column("name", String),
    column("birth_date", Date),
    column("sex", String),
    column("created_at", UtcDateTime()),
)

acquisition = table(
    "acquisition",
    column("id", Integer),
    column("uid", String),
    column("kind", String),
    column("patient_id", Integer),
    column("station_id", Integer),
    column("calibration_id", Integer),
    column("acquired_at", UtcDateTime()),
    column("operator", String),
    column("notes", Text),
)

frame = table(
    "frame",
    column("acquisition_id", Integer),
    column("index", Integer),
    column("role", String),
    column("height", Integer),
    column("width", Integer),
    column("dtype", String),
    column("sha256", String),
)
