"""A simulated patient followed over several visits, stored in the archive.

Service behind ``rasterserver simulate back --ingest`` and the demo: the station, its raster
and calibration are registered once (idempotently), and each visit's frame is ingested six
months after the previous one, like a scoliosis patient followed in clinic.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from rasterserver.archive import Archive, FrameSource
from rasterserver.catalog.models import Acquisition
from rasterserver.errors import ConflictError, NotFoundError
from rasterserver.hashing import canonical_json_sha256
from rasterserver.optics import Station
from rasterserver.simulator.back import BackParameters

#: Date of the first simulated visit; later ones follow every six months.
FIRST_VISIT = dt.datetime(2024, 1, 15, 9, 0, tzinfo=dt.UTC)
VISIT_INTERVAL = dt.timedelta(days=182)


@dataclass(frozen=True)
class SimulatedVisit:
    """One rendered visit: the back's parameters and the camera frame."""

    params: BackParameters
    image: np.ndarray
    note: str = ""


def progressed(params: BackParameters, visit: int, progression: float) -> BackParameters:
    """Return the back at visit ``visit`` (0 = first): every curve grown geometrically.

    Deviation and rotation grow by the factor ``(1 + progression) ** visit``, capped at the
    parameter limits (±120 mm, ±60°).
    """
    if visit == 0 or not params.curves:
        return params
    factor = (1.0 + progression) ** visit
    curves = tuple(
        dataclasses.replace(
            c,
            lateral_deviation=max(-120.0, min(120.0, c.lateral_deviation * factor)),
            rotation=max(-60.0, min(60.0, c.rotation * factor)),
        )
        for c in params.curves
    )
    return dataclasses.replace(params, curves=curves)


def register_station(archive: Archive, station: Station, name: str) -> None:
    """Make sure station ``name`` exists with ``station`` as its newest calibration.

    The raster is stored under a name derived from its content; a calibration identical to
    the newest one is not stored again.
    """
    try:
        archive.station(name)
    except NotFoundError:
        archive.add_station(name, description="rasterserver simulator")
    raster = station.raster_definition.to_dict()
    raster_name: str | None = f"simulator-{canonical_json_sha256(raster)[:12]}"
    try:
        archive.add_raster(raster_name, raster)  # type: ignore[arg-type]
    except ConflictError:
        raster_name = None  # stored already under another name; leave it unlinked
    calibration = station.to_dict()
    newest = archive.calibrations(name)
    if not newest or newest[-1].sha256 != canonical_json_sha256(calibration):
        # Valid from before the first simulated visit, so every visit finds it in force.
        archive.add_calibration(
            name, calibration, raster=raster_name, valid_from=FIRST_VISIT - VISIT_INTERVAL,
            notes="simulator station",
        )


def archive_visits(
    archive: Archive,
    visits: Sequence[SimulatedVisit],
    *,
    station: Station,
    patient: str,
    station_name: str = "simulator",
    log: Callable[[str], None] = lambda _line: None,
) -> list[Acquisition]:
    """Store simulated visits of ``patient`` (registered if new), six months apart.

    Parameters
    ----------
    archive : Archive
        Target archive.
    visits : sequence of SimulatedVisit
        The rendered visits, first visit first.
    station : Station
        The simulated station (its calibration is stored with the acquisitions).
    patient : str
        Patient identifier.
    station_name : str
        Station name in the catalogue.
    log : callable
        Receives one progress line per visit (no patient data).

    Returns
    -------
    list of Acquisition
    """
    try:
        archive.patient(patient)
    except NotFoundError:
        archive.add_patient(patient, name="Simulated patient")
    register_station(archive, station, station_name)
    rows = []
    for i, visit in enumerate(visits):
        main = visit.params.curves[0] if visit.params.curves else None
        summary = (
            f"{main.lateral_deviation:.1f} mm, {main.rotation:.1f}°" if main
            else "none (straight spine)"
        )
        acq = archive.ingest(
            [FrameSource(visit.image, role="raster", name=f"visit-{i + 1:02d}")],
            patient=patient,
            station=station_name,
            acquired_at=FIRST_VISIT + VISIT_INTERVAL * i,
            operator="simulator",
            notes=f"simulated back, visit {i + 1}; main curve {summary}{visit.note}",
        )
        log(f"[{i + 1}/{len(visits)}] ingested visit as acquisition {acq.uid}")
        rows.append(acq)
    return rows
