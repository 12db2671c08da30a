"""Patient and visit listings with filters: the queries behind ``GET /patients`` (by
identifier prefix and sex) and ``GET /patients/{patient}/visits`` (by date range).

The archive lists patients without filters (:meth:`rasterserver.archive.Archive.patients`);
these filtered listings are the HTTP API's, kept here so that its routers write no SQL.
"""

from __future__ import annotations

import datetime as dt
from typing import TYPE_CHECKING

from sqlalchemy import or_, select

from rasterserver.catalog.models import Patient, Visit
from rasterserver.identifiers import lookup_key

if TYPE_CHECKING:
    from rasterserver.catalog.catalog import Catalog

__all__ = ["find_patients", "patient_visits"]


def find_patients(catalog: Catalog, *, identifier_prefix: str | None = None,
                  sex: str | None = None, limit: int = 100, offset: int = 0) -> list[Patient]:
    """Patients by identifier, optionally of one sex and with identifiers starting with
    ``identifier_prefix``.

    Parameters
    ----------
    catalog : Catalog
        The catalogue.
    identifier_prefix : str, optional
        Matched as look-ups match identifiers: ignoring case and look-alike characters
        (:func:`rasterserver.identifiers.lookup_key`), or exactly as stored.
    sex : str, optional
        Only patients of this sex.
    limit, offset : int
        The page.

    Returns
    -------
    list of Patient
        Detached rows, ordered by identifier.
    """
    query = select(Patient).order_by(Patient.identifier)
    if identifier_prefix is not None:
        query = query.where(or_(
            Patient.identifier_key.startswith(lookup_key(identifier_prefix), autoescape=True),
            Patient.identifier.startswith(identifier_prefix, autoescape=True)))
    if sex is not None:
        query = query.where(Patient.sex == sex)
    with catalog.session() as s:
        return list(s.scalars(query.limit(limit).offset(offset)))


def patient_visits(catalog: Catalog, patient_id: int, *, since: dt.date | None = None,
                   until: dt.date | None = None, limit: int = 100,
                   offset: int = 0) -> list[Visit]:
    """The visits of patient ``patient_id``, oldest first.

    Parameters
    ----------
    catalog : Catalog
        The catalogue.
    patient_id : int
        Row id of the patient.
    since, until : date, optional
        On or after ``since``, before ``until``.
    limit, offset : int
        The page.

    Returns
    -------
    list of Visit
        Detached rows.
    """
    query = select(Visit).where(Visit.patient_id == patient_id)
    if since is not None:
        query = query.where(Visit.visit_date >= since)
    if until is not None:
        query = query.where(Visit.visit_date < until)
    with catalog.session() as s:
        return list(s.scalars(query.order_by(Visit.visit_date).limit(limit).offset(offset)))
