"""The SQL catalogue: patients, visits, stations, rasters, calibrations, acquisitions, frames.

:class:`~rasterserver.catalog.catalog.Catalog` is the handle everything that needs the
database takes (engine, sessions, reads outside transactions, the write lock).

Schema changes go only through the Alembic migrations in ``migrations/`` (installed as
``rasterserver_migrations``); :mod:`rasterserver.catalog.migrate` runs them, and
:mod:`rasterserver.catalog.schema` checks the revision without Alembic.

The names below are loaded on first use (PEP 562): the ORM models cost a tenth of a second
of imports that readers with SQLAlchemy Core (``rasterserver list``) do without. ``Base``
brings the HTTP API's tables (accounts, tokens, audit) and the processing jobs' with it, so
that ``Base.metadata`` is complete wherever the schema is compared or created.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rasterserver.catalog.catalog import Catalog
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

_HOMES = {
    "Catalog": "catalog",
    "make_engine": "database",
    "session_factory": "database",
    **{name: "models" for name in ("Acquisition", "Base", "Calibration", "Frame", "Patient",
                                   "Raster", "Station", "Visit")},
}

__all__ = [
    "Acquisition",
    "Base",
    "Calibration",
    "Catalog",
    "Frame",
    "Patient",
    "Raster",
    "Station",
    "Visit",
    "make_engine",
    "session_factory",
]


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    if home == "models":
        # every table in Base.metadata (see the module docstring)
        importlib.import_module(f"{__name__}.auth_models")
        importlib.import_module(f"{__name__}.job_models")
    return getattr(importlib.import_module(f"{__name__}.{home}"), name)
