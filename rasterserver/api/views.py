"""Rows to response bodies, pseudonymised for the researcher role in one place."""

from __future__ import annotations

from rasterserver.api.auth import Principal
from rasterserver.api.deps import utc
from rasterserver.api.pseudonym import Pseudonymiser
from rasterserver.api.roles import RESEARCHER
from rasterserver.api.schemas import AcquisitionOut, FrameOut, PatientOut, VisitOut
from rasterserver.catalog.models import Acquisition, Patient, Visit
from rasterserver.errors import InputError


def pseudonymised(caller: Principal) -> bool:
    """Whether ``caller`` sees pseudonyms instead of identifiers."""
    return caller.role == RESEARCHER


def resolve_patient(caller: Principal, given: str, pseudonyms: Pseudonymiser) -> str:
    """The site identifier a caller means: researchers name patients by pseudonym."""
    return pseudonyms.identifier(given) if pseudonymised(caller) else given


def patient_out(patient: Patient, caller: Principal, pseudonyms: Pseudonymiser) -> PatientOut:
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


def acquisition_out(acq: Acquisition, caller: Principal,
                    pseudonyms: Pseudonymiser) -> AcquisitionOut:
    """An acquisition as ``caller`` may see it."""
    frames = [FrameOut(index=f.index, role=f.role, height=f.height, width=f.width,
                       dtype=f.dtype, sha256=f.sha256) for f in acq.frames]
    when = utc(acq.acquired_at)
    assert when is not None
    identifier = acq.patient.identifier if acq.patient is not None else None
    if pseudonymised(caller):
        # free text may name people; the time is shifted with the patient's offset
        shifted = pseudonyms.shift_time(identifier, when) if identifier else when
        assert shifted is not None
        return AcquisitionOut(
            uid=acq.uid, kind=acq.kind,
            patient=pseudonyms.pseudonym(identifier) if identifier else None,
            station_id=acq.station_id, calibration_id=acq.calibration_id,
            acquired_at=shifted, operator=None, notes=None, frames=frames)
    return AcquisitionOut(
        uid=acq.uid, kind=acq.kind, patient=identifier, station_id=acq.station_id,
        calibration_id=acq.calibration_id, acquired_at=when, operator=acq.operator,
        notes=acq.notes, frames=frames)


def refuse_date_filters_for(caller: Principal, *values: object) -> None:
    """Researchers see shifted dates; filtering on true dates would leak them."""
    if pseudonymised(caller) and any(v is not None for v in values):
        raise InputError("date filters are not available on pseudonymised data")
