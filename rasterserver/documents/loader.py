"""The one loader: a calibration or raster document, from a file, bytes, text or a catalogue
row, to a checked :class:`~rasterserver.optics.Station` or :class:`~rasterserver.raster.Raster`.

Every place that reads a document (the commands, the pipeline, the analysis, the HTTP routes)
calls these, so a document is refused with the same sentence wherever it comes from.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from rasterserver.documents.devices import CameraDocument, DeviceDocument, ProjectorDocument
from rasterserver.documents.raster_document import RasterDocument
from rasterserver.documents.reading import read_document
from rasterserver.documents.validation import refusal, validate_calibration, validate_raster
from rasterserver.errors import InputError
from rasterserver.optics import Camera, PinholeDevice, Projector, Station
from rasterserver.raster import Raster


def _device(cls: type[PinholeDevice], doc: DeviceDocument) -> PinholeDevice:
    return cls(
        K=np.asarray(doc.K, dtype=np.float64),
        dist=doc.coefficients(),
        R=doc.rotation(),
        t=np.asarray(doc.t, dtype=np.float64),
        width=doc.width,  # type: ignore[attr-defined]
        height=doc.height,  # type: ignore[attr-defined]
    )


def _raster(doc: RasterDocument) -> Raster:
    return Raster(
        name=doc.name,
        numbers=np.array([ln.number for ln in doc.lines], dtype=np.int64),
        positions=np.array([ln.v for ln in doc.lines], dtype=np.float64),
        kinds=tuple(ln.kind for ln in doc.lines),
        widths=np.array([ln.width for ln in doc.lines], dtype=np.float64),
        window=doc.code.window,
        min_distance=doc.code.min_distance,
        description=doc.description,
    )


def device_from_document(cls: type[PinholeDevice], document: Any, *, source: str) -> PinholeDevice:
    """A camera or projector from its part of a calibration document (``cls`` says which).

    Raises
    ------
    InputError
        The device description is refused.
    """
    model = CameraDocument if issubclass(cls, Camera) else ProjectorDocument
    try:
        doc = model.model_validate(document)
    except ValidationError as exc:
        raise refusal(source, exc) from None
    return _device(cls, doc)


def calibration_from_document(document: Any, *, source: str = "calibration") -> Station:
    """The station a parsed calibration document describes, after every check.

    Parameters
    ----------
    document : Any
        The parsed JSON (``rasterserver.calibration/1``).
    source : str
        How messages name it (a file name, ``calibration clinic-1:2``).

    Returns
    -------
    Station

    Raises
    ------
    InputError
        Not an object, another kind of document, or a refused field.
    """
    doc = validate_calibration(document, source=source)
    raster = doc.raster if isinstance(doc.raster, str) else _raster(doc.raster)
    return Station(
        camera=_device(Camera, doc.camera),  # type: ignore[arg-type]
        projector=_device(Projector, doc.projector),  # type: ignore[arg-type]
        raster=raster,
        name=doc.name,
        gravity=None if doc.gravity is None else np.asarray(doc.gravity, dtype=np.float64),
    )


def raster_from_document(document: Any, *, source: str = "raster definition") -> Raster:
    """The raster a parsed ``rasterserver.raster/1`` document describes, after every check.

    Raises
    ------
    InputError
        Not an object, another kind of document, or a refused field.
    """
    return _raster(validate_raster(document, source=source))


def load_calibration_document(data: str | bytes | Path, *, source: str | None = None) -> Station:
    """Read and check a calibration: a file, its bytes or its JSON text.

    Parameters
    ----------
    data : str, bytes or Path
        The calibration (a ``str`` is JSON text, not a path).
    source : str, optional
        How messages name it; the file's name by default.

    Returns
    -------
    Station

    Raises
    ------
    InputError
        Unreadable, not JSON, or refused (see :func:`read_document`,
        :func:`calibration_from_document`).
    """
    name = source or (data.name if isinstance(data, Path) else "calibration")
    return calibration_from_document(
        read_document(data, what="calibration", source=name), source=name
    )


def load_raster_document(data: str | bytes | Path, *, source: str | None = None) -> Raster:
    """Read and check a raster definition: a file, its bytes or its JSON text.

    Raises
    ------
    InputError
        Unreadable, not JSON, or refused.
    """
    name = source or (data.name if isinstance(data, Path) else "raster definition")
    return raster_from_document(
        read_document(data, what="raster definition", source=name), source=name
    )


def stored_calibration(parameters: Any, *, label: str) -> Station:
    """The station of a calibration stored in the catalogue, checked like a file.

    Parameters
    ----------
    parameters : Any
        The row's document (``Calibration.parameters``).
    label : str
        ``STATION:VERSION``; messages name it ``calibration STATION:VERSION``.

    Returns
    -------
    Station

    Raises
    ------
    InputError
        The stored document is refused (stored before documents were checked).
    """
    return calibration_from_document(parameters, source=f"calibration {label}")


def calibration_raster(
    station: Station, definition: Any | Path | None = None, *, source: str, hint: str = ""
) -> Raster:
    """The raster a calibration uses: ``definition`` when given, else the station's own.

    Parameters
    ----------
    station : Station
        The calibration; it holds its raster inline or names a built-in one.
    definition : Any or Path, optional
        A raster definition file (a :class:`~pathlib.Path`), or a parsed document (a stored
        raster row's definition); it replaces the one the station names.
    source : str
        How messages name the calibration (``calibration clinic-1:2``, ``cal.json``).
    hint : str
        Appended to the refusal of a raster name that is not built in: what to do instead
        (``"; give its definition with --raster"``).

    Returns
    -------
    Raster

    Raises
    ------
    InputError
        The definition is refused, or the station names a raster that is not built in.
    """
    if isinstance(definition, Path):
        return load_raster_document(definition)
    if definition is not None:
        return raster_from_document(definition, source=f"the raster of {source}")
    try:
        return station.raster_definition
    except KeyError as exc:
        # get_raster's KeyError names the unknown raster and the built-in ones
        raise InputError(f"{source}: {exc.args[0]}{hint}") from None
