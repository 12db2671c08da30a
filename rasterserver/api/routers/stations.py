"""``/stations``, their ``/calibrations`` (immutable, with ETags) and ``/rasters``."""

from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query, Request, Response

from rasterserver.api.deps import (
    MAX_OFFSET,
    CallerDep,
    PageDep,
    ServicesDep,
    not_modified,
    protected_router,
    utc,
)
from rasterserver.api.schemas import (
    CalibrationIn,
    CalibrationOut,
    RasterIn,
    RasterOut,
    StationIn,
    StationOut,
)
from rasterserver.api.views import calibration_out, pseudonymised, raster_out, station_out

router = protected_router("stations")

StationName = Annotated[str, Path(max_length=100)]


@router.get("/stations", name="list_stations", response_model=list[StationOut])
def list_stations(
    svc: ServicesDep, caller: CallerDep, page: PageDep,
    name_prefix: Annotated[str | None, Query(max_length=100)] = None,
) -> list[StationOut]:
    """Stations by name (there are few: filtered and paged here)."""
    rows = [s for s in svc.archive.stations()
            if name_prefix is None or s.name.startswith(name_prefix)]
    return [station_out(s, caller) for s in rows[page.offset: page.offset + page.limit]]


@router.post("/stations", name="add_station", response_model=StationOut, status_code=201)
def add_station(body: StationIn, svc: ServicesDep) -> StationOut:
    """Register a station (a camera and projector set-up)."""
    return station_out(svc.archive.add_station(body.name, description=body.description))


@router.get("/stations/{station}", name="get_station", response_model=StationOut)
def get_station(station: StationName, svc: ServicesDep, caller: CallerDep) -> StationOut:
    """One station."""
    return station_out(svc.archive.station(station), caller)


@router.get("/stations/{station}/calibrations", name="list_calibrations",
            response_model=list[CalibrationOut])
def list_calibrations(
    station: StationName, svc: ServicesDep, caller: CallerDep, page: PageDep
) -> list[CalibrationOut]:
    """The station's calibrations, oldest version first."""
    rows = svc.archive.calibrations(station)
    return [calibration_out(c, station, caller)
            for c in rows[page.offset: page.offset + page.limit]]


@router.post("/stations/{station}/calibrations", name="add_calibration",
             response_model=CalibrationOut, status_code=201)
def add_calibration(station: StationName, body: CalibrationIn,
                    svc: ServicesDep) -> CalibrationOut:
    """Store a new calibration version of the station (never changed afterwards)."""
    row = svc.archive.add_calibration(
        station, body.parameters, residuals=body.residuals, raster=body.raster,
        valid_from=utc(body.valid_from), source_acquisition=body.source_acquisition,
        notes=body.notes, source="parameters")
    return calibration_out(row, station)


@router.get("/stations/{station}/calibrations/{version}", name="get_calibration",
            response_model=CalibrationOut, responses={304: {"description": "Not modified"}})
def get_calibration(
    station: StationName,
    version: Annotated[int, Path(ge=1, le=MAX_OFFSET)],
    request: Request, response: Response, svc: ServicesDep, caller: CallerDep,
) -> CalibrationOut | Response:
    """One calibration version; immutable, so it carries an ETag (its SHA-256)."""
    row = svc.archive.calibration(station, version)
    # the researchers' view differs (no times), so must its tag
    etag = f"calibration-{row.sha256}" + ("-pseudonymised" if pseudonymised(caller) else "")
    if (cached := not_modified(request, etag)) is not None:
        return cached
    response.headers["ETag"] = f'"{etag}"'
    response.headers["Cache-Control"] = "private, max-age=31536000, immutable"
    return calibration_out(row, station, caller)


@router.post("/rasters", name="add_raster", response_model=RasterOut, status_code=201)
def add_raster(body: RasterIn, svc: ServicesDep) -> RasterOut:
    """Store a raster diapositive definition (the same definition is stored once)."""
    return raster_out(svc.archive.add_raster(body.name, body.definition, source="definition"))


@router.get("/rasters/{name}", name="get_raster", response_model=RasterOut)
def get_raster(name: Annotated[str, Path(max_length=100)], request: Request,
               response: Response, svc: ServicesDep, caller: CallerDep) -> RasterOut | Response:
    """One raster definition, with its SHA-256 as ETag."""
    row = svc.archive.raster(name)
    etag = f"raster-{row.sha256}" + ("-pseudonymised" if pseudonymised(caller) else "")
    if (cached := not_modified(request, etag)) is not None:
        return cached
    response.headers["ETag"] = f'"{etag}"'
    return raster_out(row, caller)
