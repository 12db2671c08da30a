"""Whether frames fit the calibration that applies to them: checked at ingest, said when not.

A calibration describes one camera, so a frame of another size cannot be reconstructed with
it. Ingest refuses such a frame before anything is written (:func:`check_frames_fit`), so an
acquisition is never stored with a calibration it cannot be processed with. When no
calibration applies yet (no station given, a station without calibration, or a calibration
acquisition, whose frames are what the next calibration is computed from) the frames are
stored unchecked and :func:`calibration_notice` says so and why: the CLI prints it as a
warning, the HTTP upload returns it in ``warnings``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Protocol

import numpy as np
from sqlalchemy import select

from rasterserver.catalog.models import Calibration
from rasterserver.catalog.models import Station as StationRow
from rasterserver.errors import InputError

if TYPE_CHECKING:
    from rasterserver.archive import AcquisitionSpec, Archive

__all__ = ["calibration_notice", "check_frame_fits", "check_frames_fit"]

#: Camera shape (rows, columns) by calibration checksum: calibrations are immutable and the
#: checksum names the document, so a parsed shape stays true.
_SHAPES: dict[str, tuple[int, int]] = {}
_MAX_CACHED = 1024


def check_frame_fits(image_shape: tuple[int, ...], station: object) -> None:
    """Refuse a frame whose size differs from the calibrated camera's.

    Parameters
    ----------
    image_shape : tuple of int
        The frame's array shape ``(rows, columns, ...)``.
    station : object
        A :class:`~rasterserver.optics.Station`; anything else is not checked.

    Raises
    ------
    InputError
        With both sizes in the message.
    """
    from rasterserver.optics import Station

    if isinstance(station, Station):
        rows, cols = (int(s) for s in image_shape[:2])
        if (rows, cols) != station.camera.shape:
            raise InputError(
                f"the frame is {rows}x{cols} (rows x columns) but the calibration's camera "
                f"{station.name!r} is {station.camera.height}x{station.camera.width}: "
                "wrong calibration for this frame"
            )


def _camera_shape(sha256: str, parameters: object, label: str, station: str) -> tuple[int, int]:
    shape = _SHAPES.get(sha256)
    if shape is None:
        from rasterserver.documents import stored_calibration

        try:
            calibration = stored_calibration(parameters, label=label)
        except InputError as exc:
            # stored before documents were checked: it would fail every acquisition later
            raise InputError(
                f"{exc}; frames are checked against it, so store a corrected calibration of "
                f"station {station!r} (a new version) first"
            ) from None
        shape = calibration.camera.shape
        if len(_SHAPES) >= _MAX_CACHED:
            _SHAPES.clear()
        _SHAPES[sha256] = shape
    return shape


def check_frames_fit(
    archive: Archive,
    specs: Sequence[AcquisitionSpec],
    calibration_ids: Sequence[int | None],
    frames: Sequence[Sequence[np.ndarray]],
) -> None:
    """Refuse acquisitions whose frames do not have the size of their calibration's camera.

    Called by ingest after the frames are decoded and before anything is written.
    Calibration acquisitions are not checked: their frames make the next calibration, which
    may be of a new camera.

    Parameters
    ----------
    archive : Archive
        Where the calibrations are.
    specs : sequence of AcquisitionSpec
        The acquisitions.
    calibration_ids : sequence of int or None
        The calibration that applies to each (None: none).
    frames : sequence of sequences of numpy.ndarray
        Each acquisition's decoded frames, in the order of its ``frames``.

    Raises
    ------
    InputError
        Naming the frame, its size, the calibration and its camera's size.
    """
    wanted = {
        cid
        for spec, cid in zip(specs, calibration_ids, strict=True)
        if cid is not None and spec.kind != "calibration"
    }
    if not wanted:
        return
    # one statement each, outside a transaction: calibrations are immutable
    with archive.reading() as conn:
        rows = conn.execute(
            select(Calibration.id, Calibration.version, Calibration.sha256, StationRow.name)
            .join(StationRow, StationRow.id == Calibration.station_id)
            .where(Calibration.id.in_(wanted))
        ).all()
    # the documents only of calibrations not parsed before (a JSON column is not free)
    documents: dict[int, object] = {}
    if unknown := [row.id for row in rows if row.sha256 not in _SHAPES]:
        with archive.reading() as conn:
            query = select(Calibration.id, Calibration.parameters)
            documents = dict(conn.execute(query.where(Calibration.id.in_(unknown))).all())
    cameras = {
        row.id: (
            _camera_shape(row.sha256, documents.get(row.id), f"{row.name}:{row.version}", row.name),
            f"{row.name}:{row.version}",
        )
        for row in rows
    }
    for spec, cid, arrays in zip(specs, calibration_ids, frames, strict=True):
        if cid not in cameras or spec.kind == "calibration":
            continue
        (height, width), label = cameras[cid]
        for k, (source, array) in enumerate(zip(spec.frames, arrays, strict=True)):
            rows_, cols = array.shape[:2]
            if (rows_, cols) != (height, width):
                name = source.name or f"frame {k}"
                raise InputError(
                    f"{name}: the frame is {rows_}x{cols} (rows x columns) but the camera of "
                    f"calibration {label}, which applies to it, is {height}x{width}: a frame "
                    "of another camera or the wrong station; nothing stored"
                )


class _Stored(Protocol):
    # read-only, so that a catalogue row and an AcquisitionInfo (a named tuple) both fit
    @property
    def kind(self) -> str: ...

    @property
    def station_id(self) -> int | None: ...

    @property
    def calibration_id(self) -> int | None: ...


def calibration_notice(archive: Archive, acquisition: _Stored) -> str | None:
    """Why no calibration applies to a stored acquisition, or None when one does.

    Parameters
    ----------
    archive : Archive
        The archive it is stored in.
    acquisition : Acquisition or AcquisitionInfo
        Anything with its ``kind``, ``station_id`` and ``calibration_id``.

    Returns
    -------
    str or None
        A sentence saying which case and that the frame size was not checked.
    """
    if acquisition.kind == "calibration":
        return (
            "a calibration acquisition: its frames are not checked against a calibration "
            "(they are what the next calibration is computed from)"
        )
    if acquisition.station_id is None:
        return (
            "no station given, so no calibration applies: the frame size was not checked, and "
            "processing needs --calibration STATION:VERSION"
        )
    if acquisition.calibration_id is None:
        with archive.session() as s:
            station = s.get(StationRow, acquisition.station_id)
            name = station.name if station is not None else "?"
        return (
            f"station {name!r} has no calibration yet, so none applies: the frame size was not "
            "checked; store one (`rasterserver station add-calibration` or `rasterserver "
            f"calibrate`), then process with --calibration {name}:VERSION"
        )
    return None
