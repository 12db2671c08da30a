"""The catalogue's closed vocabularies, without SQLAlchemy: commands check options against
them before opening anything (the models' check constraints use the same tuples)."""

from __future__ import annotations

__all__ = ["ACQUISITION_KINDS", "FRAME_ROLES", "SEXES"]

SEXES = ("female", "male", "other", "unknown")
FRAME_ROLES = ("raster", "projector-off", "projector-on", "dark", "other")
ACQUISITION_KINDS = ("patient", "calibration", "test")
