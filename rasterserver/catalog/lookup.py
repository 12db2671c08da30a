"""Finding catalogue rows by the names people type (:mod:`rasterserver.identifiers`).

A name is found as stored, or failing that by its comparison key
(:func:`~rasterserver.identifiers.lookup_key`: case and look-alike characters folded). Exact
first, so that names stored before the key was unique, look-alikes of each other, each keep
their own rows. The archive service, the accounts and the audit trail look names up here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sqlalchemy import BindParameter, ColumnElement, func, select

from rasterserver.catalog.columns import patient
from rasterserver.identifiers import lookup_key

if TYPE_CHECKING:
    from sqlalchemy.orm import InstrumentedAttribute, Session

# The patient table through its light Core view (rasterserver.catalog.columns): the listing
# statements built from patient_id_of load without the ORM.

__all__ = ["patient_id_of", "stored_name"]


def patient_id_of(
    identifier: str | BindParameter[str], key: str | BindParameter[str] | None = None
) -> ColumnElement[int]:
    """The id of the patient a user means by ``identifier``, as an SQL expression.

    The patient registered under exactly this identifier; failing that, the one whose
    ``identifier_key`` is the identifier's comparison key. Two indexed look-ups in one
    statement, evaluated once (they do not depend on the outer query): no round trip.

    Parameters
    ----------
    identifier : str or BindParameter
        The identifier as given.
    key : str or BindParameter, optional
        Its comparison key; computed from a plain ``identifier`` when not given.

    Returns
    -------
    ColumnElement
        The patient's id, or NULL for an unknown patient.
    """
    if key is None:
        if not isinstance(identifier, str):
            raise TypeError("give the key of a bound identifier")
        key = lookup_key(identifier)
    return func.coalesce(
        select(patient.c.id).where(patient.c.identifier == identifier).scalar_subquery(),
        select(patient.c.id).where(patient.c.identifier_key == key).scalar_subquery(),
    )


def stored_name(
    session: Session, column: InstrumentedAttribute[str], name: str, *, exact: bool = True
) -> str | None:
    """The name stored in ``column`` that ``name`` means, or None.

    The same name if ``exact`` and there is one, else one with the same comparison key. For
    the small tables (stations, rasters, accounts), whose names are compared in Python;
    patients have an indexed key column (:func:`patient_id_of`).

    Parameters
    ----------
    session : Session
        A catalogue session.
    column : InstrumentedAttribute
        The name column, e.g. ``Station.name``.
    name : str
        The name as given.
    exact : bool, default True
        Look for the name itself first; with False only look-alikes are looked for (to
        refuse a new name that another one resembles).

    Returns
    -------
    str or None
    """
    if exact and session.scalar(select(column).where(column == name)) is not None:
        return name
    key = lookup_key(name)
    for (stored,) in session.execute(select(column).order_by(column)):
        if lookup_key(stored) == key:
            return stored
    return None
