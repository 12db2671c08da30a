"""Store a computed calibration in the archive: frames as an acquisition, then a version.

Order matters for an explainable archive: the six frames are ingested first (one
``kind="calibration"`` acquisition, roles ``projector-off`` / ``projector-on``), then the
calibration row that names that acquisition as its source. A crash in between leaves a
calibration acquisition without a calibration, which is harmless and can be calibrated again.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from sqlalchemy import select

from rasterserver.archive import Archive, FrameSource
from rasterserver.calibration.station_calibration import CalibrationFrames, StationCalibration
from rasterserver.catalog.models import Raster as RasterRow
from rasterserver.errors import NotFoundError
from rasterserver.hashing import canonical_json_sha256
from rasterserver.raster import Raster

__all__ = ["StoredCalibration", "calibration_frame_sources", "ensure_raster", "store_calibration"]


@dataclass(frozen=True)
class StoredCalibration:
    """Where a calibration went.

    Attributes
    ----------
    station : str
        Station name.
    version : int
        The new calibration version.
    acquisition : str
        uid of the calibration acquisition holding the frames.
    raster : str
        Name of the stored raster definition.
    """

    station: str
    version: int
    acquisition: str
    raster: str


def calibration_frame_sources(frames: CalibrationFrames) -> list[FrameSource]:
    """The frames as ingest sources, configuration by configuration, off before on."""
    sources = []
    for k in sorted(set(frames.off) | set(frames.on)):
        for state, have in (("off", frames.off), ("on", frames.on)):
            if k in have:
                name = frames.names.get((k, state), f"config{k}-projector-{state}.png")
                sources.append(FrameSource(have[k], role=f"projector-{state}", name=name))
    return sources


def ensure_raster(archive: Archive, raster: Raster) -> str:
    """Store ``raster``'s definition unless it is stored already; return its stored name."""
    definition = raster.to_dict()
    digest = canonical_json_sha256(definition)
    with archive.session() as s:
        same = s.scalar(select(RasterRow).where(RasterRow.sha256 == digest))
        if same is not None:
            return same.name
    return archive.add_raster(raster.name, definition).name


def store_calibration(
    archive: Archive,
    result: StationCalibration,
    frames: CalibrationFrames,
    *,
    station: str,
    valid_from: dt.datetime | None = None,
    notes: str = "",
    create_station: bool = True,
) -> StoredCalibration:
    """Ingest the frames and store ``result`` as ``station``'s next calibration version.

    Parameters
    ----------
    archive : Archive
        Where to store.
    result : StationCalibration
        From :func:`~rasterserver.calibration.calibrate_station`.
    frames : CalibrationFrames
        The frames it was computed from.
    station : str
        Station name.
    valid_from : datetime, optional
        From when the calibration applies (default: now).
    notes : str
        Free text for the calibration row.
    create_station : bool
        Register an unknown station instead of refusing.

    Returns
    -------
    StoredCalibration
    """
    try:
        archive.station(station)
    except NotFoundError:
        if not create_station:
            raise
        archive.add_station(station, description="registered by rasterserver calibrate")
    raster = result.station.raster_definition
    raster_name = ensure_raster(archive, raster)
    acquisition = archive.ingest(
        calibration_frame_sources(frames),
        patient=None,
        kind="calibration",
        station=station,
        notes="control-point frames of a station calibration",
    )
    parameters = result.station.to_dict()
    parameters["name"] = station
    row = archive.add_calibration(
        station,
        parameters,
        residuals=result.residuals_dict(),
        raster=raster_name,
        valid_from=valid_from,
        source_acquisition=acquisition.uid,
        notes=notes
        or (
            f"camera {result.camera.rms:.3f} px rms over {len(result.point_ids)} control "
            f"points; projector {result.projector_rms_mm:.3f} mm rms over "
            f"{result.projector.residuals.size} raster peaks"
        ),
    )
    return StoredCalibration(station, row.version, acquisition.uid, raster_name)
