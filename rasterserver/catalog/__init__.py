"""The SQL catalogue: patients, visits, stations, rasters, calibrations, acquisitions, frames.

Schema changes go only through the Alembic migrations in ``migrations/`` (installed as
``rasterserver_migrations``); :mod:`rasterserver.catalog.migrate` runs them.
"""

from rasterserver.catalog.database import make_engine, session_factory
from rasterserver.catalog.models import (
    Acquisition,
    Base,
    Calibration,
    Frame,
    Patient,
    Raster,
    Station,
    Visit,
)

__all__ = [
    "Acquisition",
    "Base",
    "Calibration",
    "Frame",
    "Patient",
    "Raster",
    "Station",
    "Visit",
    "make_engine",
    "session_factory",
]

# The HTTP API's tables (accounts, tokens, audit) must be in Base.metadata wherever the
# schema is compared or created, so they are imported with the catalogue.
from rasterserver.catalog import auth_models as auth_models

# Processing jobs and their tasks (migration 0012), for the same reason.
from rasterserver.catalog import job_models as job_models
