"""The choices of an export (format, what, frame): the options of ``rasterserver export``.

Apart from :mod:`rasterserver.export`, which needs OpenCV, NumPy and open3d to write files,
because the command line needs these enumerations to build its options (and ``--help``) and
should not load those packages to do so. :mod:`rasterserver.export` re-exports them.
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["ExportFormat", "ExportFrame", "ExportWhat"]


class ExportFormat(StrEnum):
    """File format of an export."""

    ply = "ply"
    obj = "obj"
    stl = "stl"
    csv = "csv"


class ExportWhat(StrEnum):
    """Which stored result to export."""

    mesh = "mesh"
    points = "points"
    smoothed = "smoothed"


class ExportFrame(StrEnum):
    """Coordinate frame of an export (see :mod:`rasterserver.export`)."""

    station = "station"
    patient = "patient"
