"""The calibration and raster definition documents: read and validated here, and only here.

A calibration (``rasterserver.calibration/1``) and a raster definition
(``rasterserver.raster/1``) reach the server as files on the command line, as JSON bodies of
the HTTP API, and as rows of the catalogue. Every one of those readers goes through this
package, so a document is accepted or refused for the same reasons everywhere:

:func:`read_document` (:mod:`.reading`)
    JSON text (a file, bytes or a string) to a Python value, with a sentence instead of a
    traceback for a missing file, a directory, binary or non-UTF-8 bytes, bad JSON, JSON
    nested too deeply, duplicate keys or a file too large to be a document.
:func:`calibration_from_document`, :func:`raster_from_document` (:mod:`.loader`)
    A parsed document to a :class:`~rasterserver.optics.Station` or a
    :class:`~rasterserver.raster.Raster`, validated by the typed models (:mod:`.validation`).
:func:`load_calibration_document`, :func:`load_raster_document`
    Both steps, for a file, its bytes or its text.
:func:`stored_calibration`, :func:`calibration_raster`
    A calibration row of the catalogue, and the raster a calibration uses (stored, given as a
    file, inline or built in).

The models (:class:`CalibrationDocument` in :mod:`.calibration_document`,
:class:`RasterDocument` in :mod:`.raster_document`, the devices in :mod:`.devices`, their field
types in :mod:`.fields`) are the format's definition: their JSON Schema is published in the
OpenAPI document, in ``docs/schemas/``, and the field tables of ``docs/formats.md`` are
generated from it (:mod:`.tables`). Besides types and required fields they check what makes a
document usable: finite numbers only, ``K`` upper triangular with positive focal lengths and
last row ``[0, 0, 1]``, ``R`` a rotation (within :data:`ROTATION_TOL`), positive image sizes,
distortion coefficients OpenCV can hold and a lens model that does not fold back inside the
image, camera and projector centres apart across the raster lines, a raster whose lines
increase and whose code identifies positions as declared.

Every refusal is an :class:`~rasterserver.errors.InputError` naming the source and the field,
e.g. ``cal.json: camera.K: focal lengths must be positive (fx = 0, fy = 0)``.
"""

from __future__ import annotations

from rasterserver.documents.calibration_document import CalibrationDocument
from rasterserver.documents.devices import CameraDocument, DeviceDocument, ProjectorDocument
from rasterserver.documents.fields import GRAVITY_TOL, MAX_MAGNITUDE, ROTATION_TOL
from rasterserver.documents.loader import (
    calibration_from_document,
    calibration_raster,
    device_from_document,
    load_calibration_document,
    load_raster_document,
    raster_from_document,
    stored_calibration,
)
from rasterserver.documents.raster_document import RasterCode, RasterDocument, RasterLine
from rasterserver.documents.reading import MAX_DOCUMENT_BYTES, read_document
from rasterserver.documents.tables import (
    fill_format_tables,
    format_tables,
    json_schemas,
    write_json_schemas,
)
from rasterserver.documents.validation import validate_calibration, validate_raster
from rasterserver.optics import CALIBRATION_FORMAT
from rasterserver.raster import RASTER_FORMAT

__all__ = [
    "CALIBRATION_FORMAT",
    "GRAVITY_TOL",
    "MAX_DOCUMENT_BYTES",
    "MAX_MAGNITUDE",
    "RASTER_FORMAT",
    "ROTATION_TOL",
    "CalibrationDocument",
    "CameraDocument",
    "DeviceDocument",
    "ProjectorDocument",
    "RasterCode",
    "RasterDocument",
    "RasterLine",
    "calibration_from_document",
    "calibration_raster",
    "device_from_document",
    "fill_format_tables",
    "format_tables",
    "json_schemas",
    "load_calibration_document",
    "load_raster_document",
    "raster_from_document",
    "read_document",
    "stored_calibration",
    "validate_calibration",
    "validate_raster",
    "write_json_schemas",
]
