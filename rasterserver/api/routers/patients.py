"""``/patients`` and their ``/visits``; researchers see pseudonyms and shifted dates."""

from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query

from rasterserver.api.deps import CallerDep, NoteDep, PageDep, ServicesDep, protected_router
from rasterserver.api.fields import Day, Sex
from rasterserver.api.schemas import PatientIn, PatientOut, VisitOut
from rasterserver.api.views import (
    patient_out,
    pseudonymised,
    refuse_date_filters_for,
    resolve_patient,
    visit_out,
)
from rasterserver.errors import InputError
from rasterserver.services.patients import find_patients, patient_visits

router = protected_router("patients")

PatientRef = Annotated[str, Path(
    min_length=1, max_length=64,
    description="Site identifier (researchers: pseudonym), percent-encoded; differences of "
    "case or look-alike characters are ignored.")]


@router.get("/patients", name="list_patients", response_model=list[PatientOut])
def list_patients(
    svc: ServicesDep, caller: CallerDep, note: NoteDep, page: PageDep,
    identifier_prefix: Annotated[str | None, Query(
        max_length=64, description="Identifiers starting with this (not for researchers).")]
    = None,
    sex: Annotated[Sex | None, Query()] = None,
) -> list[PatientOut]:
    """Patients by identifier, optionally filtered by identifier prefix and sex."""
    if identifier_prefix is None and sex is None:
        rows = svc.archive.patients(limit=page.limit, offset=page.offset)
    else:
        if identifier_prefix is not None and pseudonymised(caller):
            raise InputError("researchers cannot filter on identifiers")
        rows = find_patients(svc.catalog, identifier_prefix=identifier_prefix, sex=sex,
                             limit=page.limit, offset=page.offset)
    for p in rows:
        note.touch(p.id)
    return [patient_out(p, caller, svc.pseudonyms) for p in rows]


@router.post("/patients", name="add_patient", response_model=PatientOut, status_code=201)
def add_patient(body: PatientIn, svc: ServicesDep, caller: CallerDep,
                note: NoteDep) -> PatientOut:
    """Register a patient under the site's identifier."""
    row = svc.archive.add_patient(body.identifier, name=body.name,
                                  birth_date=body.birth_date, sex=body.sex)
    note.touch(row.id)
    return patient_out(row, caller, svc.pseudonyms)


# ``:path`` so that identifiers registered before '/' was refused (rasterserver.identifiers)
# stay reachable, as /patients/SL%2F01 (the server decodes %2F before routing). The visits
# route comes first: it is the one /patients/A/visits means.
@router.get("/patients/{patient:path}/visits", name="list_visits", response_model=list[VisitOut])
def list_visits(
    patient: PatientRef, svc: ServicesDep, caller: CallerDep, note: NoteDep, page: PageDep,
    since: Annotated[Day | None, Query(description="On or after, YYYY-MM-DD (not for "
                                             "researchers).")] = None,
    until: Annotated[Day | None, Query(description="Before, YYYY-MM-DD (not for researchers).")]
    = None,
) -> list[VisitOut]:
    """The patient's visits, oldest first, optionally in a date range."""
    refuse_date_filters_for(caller, since, until)
    identifier = resolve_patient(caller, patient, svc.pseudonyms)
    row = svc.archive.patient(identifier)
    note.touch(row.id)
    visits = patient_visits(svc.catalog, row.id, since=since, until=until, limit=page.limit,
                            offset=page.offset)
    return [visit_out(v, row.identifier, caller, svc.pseudonyms) for v in visits]


@router.get("/patients/{patient:path}", name="get_patient", response_model=PatientOut)
async def get_patient(patient: PatientRef, svc: ServicesDep, caller: CallerDep,
                note: NoteDep) -> PatientOut:
    """One patient."""
    # async, like the acquisitions' metadata reads (see there)
    row = await svc.read(svc.archive.patient_info,
                         resolve_patient(caller, patient, svc.pseudonyms))
    note.touch(row.id)
    return patient_out(row, caller, svc.pseudonyms)
