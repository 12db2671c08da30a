"""Rows to response bodies, pseudonymised for the researcher role in one place.

The routers hand the records the services return to these functions; they do not touch
the catalogue's ORM types themselves.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from typing import Any

import orjson
from fastapi import Response

from rasterserver.api.deps import utc
from rasterserver.api.errors import scrub_paths
from rasterserver.api.roles import RESEARCHER
from rasterserver.api.schemas import (
    CalibrationOut,
    PatientOut,
    RasterOut,
    ResultOut,
    RunOut,
    StationOut,
    VisitOut,
)
from rasterserver.archive import AcquisitionInfo, PatientInfo
from rasterserver.catalog.models import (
    Calibration,
    Patient,
    PipelineRun,
    Raster,
    StageResult,
    Station,
    Visit,
)
from rasterserver.errors import InputError
from rasterserver.services.auth import Principal
from rasterserver.services.pseudonyms import Pseudonymiser


def pseudonymised(caller: Principal) -> bool:
    """Whether ``caller`` sees pseudonyms instead of identifiers."""
    return caller.role == RESEARCHER


def resolve_patient(caller: Principal, given: str, pseudonyms: Pseudonymiser) -> str:
    """The site identifier a caller means: researchers name patients by pseudonym."""
    return pseudonyms.identifier(given) if pseudonymised(caller) else given


def patient_out(patient: Patient | PatientInfo, caller: Principal,
                pseudonyms: Pseudonymiser) -> PatientOut:
    """The patient as ``caller`` may see it."""
    created = utc(patient.created_at)
    assert created is not None
    if pseudonymised(caller):
        return PatientOut(id=pseudonyms.pseudonym(patient.identifier), pseudonymised=True,
                          sex=patient.sex,
                          created_at=pseudonyms.shift_time(patient.identifier, created))
    return PatientOut(id=patient.identifier, pseudonymised=False, name=patient.name,
                      birth_date=patient.birth_date, sex=patient.sex, created_at=created)


def visit_out(visit: Visit, identifier: str, caller: Principal,
              pseudonyms: Pseudonymiser) -> VisitOut:
    """A visit as ``caller`` may see it (date shifted and no notes for researchers)."""
    if pseudonymised(caller):
        day = pseudonyms.shift_date(identifier, visit.visit_date)
        assert day is not None
        return VisitOut(visit_date=day, notes=None)
    return VisitOut(visit_date=visit.visit_date, notes=visit.notes)


def acquisition_body(info: AcquisitionInfo, caller: Principal,
                     pseudonyms: Pseudonymiser) -> dict[str, Any]:
    """An acquisition as ``caller`` may see it: the JSON form of
    :class:`~rasterserver.api.schemas.AcquisitionOut`.

    Built as a plain dict for :func:`json_response`: lists of a hundred acquisitions are the
    API's busiest answer, and validating them through pydantic models cost more than the
    catalogue query. The OpenAPI schema is still that model, and the property
    tests check every answer against it.
    """
    frames = [{"index": f.index, "role": f.role, "height": f.height, "width": f.width,
               "dtype": f.dtype, "sha256": f.sha256} for f in info.frames]
    identifier = info.patient
    if pseudonymised(caller):
        # free text may name people; the time is shifted with the patient's offset
        return {"uid": info.uid, "kind": info.kind,
                "patient": pseudonyms.pseudonym(identifier) if identifier else None,
                "station_id": info.station_id, "calibration_id": info.calibration_id,
                "acquired_at": (pseudonyms.shift_time(identifier, info.acquired_at)
                                if identifier else info.acquired_at),
                "operator": None, "notes": None, "frames": frames}
    return {"uid": info.uid, "kind": info.kind, "patient": identifier,
            "station_id": info.station_id, "calibration_id": info.calibration_id,
            "acquired_at": info.acquired_at, "operator": info.operator, "notes": info.notes,
            "frames": frames}


def patient_clock(caller: Principal, identifier: str | None,
                  pseudonyms: Pseudonymiser) -> Callable[[dt.datetime | None], dt.datetime | None]:
    """How ``caller`` sees the times of records about the patient ``identifier``.

    Every time a researcher can see that belongs to a patient's data (when an acquisition
    was made, when its results were computed, when its pipeline runs started and ended) is
    shifted by that patient's offset: left true, any one of them would give the offset away
    (an acquisition processed minutes after it was taken dates itself). Others see UTC.
    Records without a patient (calibration acquisitions) keep their times.
    """
    if not pseudonymised(caller) or not identifier:
        return utc

    def shifted(when: dt.datetime | None) -> dt.datetime | None:
        return pseudonyms.shift_time(identifier, utc(when))

    return shifted


def json_response(content: Any, status_code: int = 200) -> Response:
    """A JSON response serialised by orjson, with times written as pydantic writes them."""
    return Response(orjson.dumps(content, option=orjson.OPT_UTC_Z), status_code=status_code,
                    media_type="application/json")


def refuse_date_filters_for(caller: Principal, *values: object) -> None:
    """Researchers see shifted dates; filtering on true dates would leak them."""
    if pseudonymised(caller) and any(v is not None for v in values):
        raise InputError("date filters are not available on pseudonymised data")


#: How a caller sees a record's times (see :func:`patient_clock`).
Clock = Callable[[dt.datetime | None], dt.datetime | None]


def result_out(row: StageResult, clock: Clock) -> ResultOut:
    """A stored stage result, its times as ``clock`` shows them (:func:`patient_clock`)."""
    return ResultOut(
        id=row.id, stage=row.stage, plugin=row.plugin, plugin_version=row.plugin_version,
        plugin_package=row.plugin_package, frame_index=row.frame_index, params=row.params,
        params_hash=row.params_hash, chain_key=row.chain_key,
        input_checksum=row.input_checksum, output_checksum=row.output_checksum,
        record_kind=row.record_kind, calibration_id=row.calibration_id, reason=row.reason,
        package_version=row.package_version, duration_s=row.duration_s,
        created_at=clock(row.created_at))


def run_out(row: PipelineRun, clock: Clock, archive_root: object) -> RunOut:
    """A pipeline run, its times as ``clock`` shows them, paths in its error scrubbed."""
    return RunOut(id=row.id, status=row.status, chain=row.chain,
                  started_at=clock(row.started_at),
                  finished_at=clock(row.finished_at),
                  error=scrub_paths(row.error, archive_root),
                  computed=row.computed, reused=row.reused)


# Researchers get no times of stations, calibrations and rasters: the period a calibration
# applied brackets the true dates of the acquisitions made with it (a researcher sees which
# calibration each used), which would undo the patients' date shifts.


def station_out(row: Station, caller: Principal | None = None) -> StationOut:
    """A station as ``caller`` may see it (no times for researchers, see above)."""
    hide = caller is not None and pseudonymised(caller)
    return StationOut(name=row.name, description=row.description,
                      created_at=None if hide else utc(row.created_at))


def calibration_out(row: Calibration, station: str,
                    caller: Principal | None = None) -> CalibrationOut:
    """A calibration of ``station`` as ``caller`` may see it."""
    hide = caller is not None and pseudonymised(caller)
    return CalibrationOut(
        station=station, version=row.version, sha256=row.sha256, raster_id=row.raster_id,
        parameters=row.parameters, residuals=row.residuals,
        valid_from=None if hide else utc(row.valid_from), notes=None if hide else row.notes,
        created_at=None if hide else utc(row.created_at))


def raster_out(row: Raster, caller: Principal | None = None) -> RasterOut:
    """A raster as ``caller`` may see it."""
    hide = caller is not None and pseudonymised(caller)
    return RasterOut(name=row.name, sha256=row.sha256, definition=row.definition,
                     created_at=None if hide else utc(row.created_at))
