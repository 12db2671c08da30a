"""Reading the catalogue's acquisitions and patients as plain records, without ORM objects.

What ``rasterserver list`` and the HTTP API's lists and metadata reads show: one statement
each (a page of acquisitions joined to its frames), built once with bound parameters, run
outside a transaction (:meth:`~rasterserver.catalog.catalog.Catalog.reading`), its rows
grouped into named tuples. Building full ORM objects would cost more than the query.
"""

from __future__ import annotations

import datetime as dt
import functools
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

from sqlalchemy import Integer, Select, bindparam, select

# _t: the tables' light Core views (the parameters are called patient, kind, ...)
from rasterserver.catalog.columns import acquisition as acquisition_t
from rasterserver.catalog.columns import frame as frame_t
from rasterserver.catalog.columns import patient as patient_t
from rasterserver.catalog.lookup import patient_id_of
from rasterserver.errors import NotFoundError
from rasterserver.identifiers import lookup_key
from rasterserver.times import require_zone

if TYPE_CHECKING:
    from rasterserver.catalog.catalog import Catalog

__all__ = [
    "PATIENT_OF",
    "AcquisitionInfo",
    "FrameInfo",
    "PatientInfo",
    "check_range",
    "find",
    "info",
    "patient_info",
    "patient_params",
]


# Named tuples rather than frozen dataclasses: a list of a hundred acquisitions builds a
# few hundred of them per request, and a frozen dataclass costs several times more to make.
class FrameInfo(NamedTuple):
    """A frame's catalogue entry, as :func:`find` and :func:`info` give it."""

    index: int  # type: ignore[assignment]  # the frame's index, hiding tuple.index
    role: str
    height: int
    width: int
    dtype: str
    sha256: str


class PatientInfo(NamedTuple):
    """A patient's catalogue entry read without ORM objects (:func:`patient_info`)."""

    id: int
    identifier: str
    name: str
    birth_date: dt.date | None
    sex: str
    created_at: dt.datetime


class AcquisitionInfo(NamedTuple):
    """An acquisition's catalogue entry read without ORM objects.

    What a listing, a search or a metadata request shows; ``acquired_at`` is in UTC.
    """

    uid: str
    kind: str
    patient_id: int | None
    patient: str | None
    station_id: int | None
    calibration_id: int | None
    acquired_at: dt.datetime
    operator: str
    notes: str
    frames: tuple[FrameInfo, ...]


def check_range(since: dt.datetime | None, until: dt.datetime | None) -> None:
    """Refuse listing bounds without a time zone (their meaning would depend on the backend)."""
    for value, what in ((since, "since"), (until, "until")):
        if value is not None:
            require_zone(value, what)


# The statements of find() and info() are built once, with bound parameters: building a
# SQLAlchemy statement costs more Python than running it on a page of a hundred rows.
_INFO_COLUMNS = (
    acquisition_t.c.id, acquisition_t.c.uid, acquisition_t.c.kind, acquisition_t.c.patient_id,
    patient_t.c.identifier, acquisition_t.c.station_id, acquisition_t.c.calibration_id,
    acquisition_t.c.acquired_at, acquisition_t.c.operator, acquisition_t.c.notes,
)
_FRAME_COLUMNS = (frame_t.c.index, frame_t.c.role, frame_t.c.height, frame_t.c.width,
                  frame_t.c.dtype, frame_t.c.sha256)


def patient_params(identifier: str) -> dict[str, str]:
    """The bound values of :data:`PATIENT_OF`."""
    return {"identifier": identifier, "identifier_key": lookup_key(identifier)}


PATIENT_OF = patient_id_of(bindparam("identifier"), bindparam("identifier_key"))
_PATIENT_ID = select(patient_t.c.id).where(patient_t.c.id == PATIENT_OF)
_PATIENT_INFO = select(patient_t.c.id, patient_t.c.identifier, patient_t.c.name,
                       patient_t.c.birth_date, patient_t.c.sex,
                       patient_t.c.created_at).where(patient_t.c.id == PATIENT_OF)


def _with_frames(page: Select[Any]) -> Select[Any]:
    """``page`` (the info columns, ordered) joined to its frames, in the same order."""
    sub = page.subquery()
    return (select(sub, *_FRAME_COLUMNS)
            .outerjoin(frame_t, frame_t.c.acquisition_id == sub.c.id)
            .order_by(sub.c.acquired_at.desc(), sub.c.id.desc(), frame_t.c.index))


@functools.cache
def _find_statement(patient: bool, since: bool, until: bool, kind: bool) -> Select[Any]:
    """The statement of :func:`find` for one combination of filters."""
    page = select(*_INFO_COLUMNS).outerjoin(patient_t, patient_t.c.id == acquisition_t.c.patient_id)
    if patient:  # by identifier, in the same query: no round trip to look up the id first
        page = page.where(acquisition_t.c.patient_id == PATIENT_OF)
    if since:
        page = page.where(acquisition_t.c.acquired_at >= bindparam("since"))
    if until:
        page = page.where(acquisition_t.c.acquired_at < bindparam("until"))
    if kind:
        page = page.where(acquisition_t.c.kind == bindparam("kind"))
    page = (page.order_by(acquisition_t.c.acquired_at.desc(), acquisition_t.c.id.desc())
            .limit(bindparam("limit", type_=Integer)).offset(bindparam("offset", type_=Integer)))
    return _with_frames(page)


_INFO_BY_UID = _with_frames(
    select(*_INFO_COLUMNS).outerjoin(patient_t, patient_t.c.id == acquisition_t.c.patient_id)
    .where(acquisition_t.c.uid == bindparam("uid")).order_by(acquisition_t.c.acquired_at.desc(),
                                                         acquisition_t.c.id.desc()))


def _infos(rows: Iterable[Sequence[Any]]) -> list[AcquisitionInfo]:
    """Group the rows of a :func:`_with_frames` statement (one per frame) by acquisition."""
    grouped: list[tuple[Sequence[Any], list[FrameInfo]]] = []
    current: int | None = None
    for row in rows:
        if row[0] != current:
            current = row[0]
            grouped.append((row, []))
        if row[10] is not None:  # an acquisition without frames has one row of NULLs
            # _make: a named tuple straight from a sequence, without the generated __new__
            grouped[-1][1].append(FrameInfo._make(row[10:]))
    return [
        # uid, kind, patient id, identifier, station, calibration, time (UTC: UtcDateTime),
        # operator, notes
        AcquisitionInfo._make((*r[1:10], tuple(frames)))
        for r, frames in grouped
    ]


def find(
    catalog: Catalog,
    *,
    patient: str | None = None,
    since: dt.datetime | None = None,
    until: dt.datetime | None = None,
    kind: str | None = None,
    limit: int = 10_000,
    offset: int = 0,
) -> list[AcquisitionInfo]:
    """Find acquisitions with their frames, newest first, as plain records.

    One query (the page joined to its frames) and no ORM objects: what the HTTP API's
    lists and ``rasterserver list`` show, and cheap enough for a month of a clinic's work,
    where building full :class:`Acquisition` objects would cost more than the query.
    ``since`` is inclusive and ``until`` exclusive (both with their time zone).
    """
    check_range(since, until)
    params: dict[str, Any] = {"identifier": patient, "since": since, "until": until,
                              "kind": kind, "limit": limit, "offset": offset}
    if patient is not None:
        params["identifier_key"] = lookup_key(patient)
    query = _find_statement(*(params[k] is not None
                              for k in ("identifier", "since", "until", "kind")))
    with catalog.reading() as conn:
        found = _infos(conn.execute(query, params))
        # an empty page of an unknown patient is an error; one more query tells which
        if not found and patient is not None and conn.execute(
                _PATIENT_ID, patient_params(patient)).first() is None:
            raise NotFoundError(
                "unknown patient: register it first with `rasterserver patient add`")
    return found

def info(catalog: Catalog, uid: str) -> AcquisitionInfo:
    """The catalogue entry of acquisition ``uid`` (see :func:`find`).

    Raises
    ------
    NotFoundError
        No such acquisition.
    """
    with catalog.reading() as conn:
        found = _infos(conn.execute(_INFO_BY_UID, {"uid": uid}))
    if not found:
        raise NotFoundError(f"unknown acquisition {uid}")
    return found[0]

def patient_info(catalog: Catalog, identifier: str) -> PatientInfo:
    """The catalogue entry of the patient with ``identifier``, read without ORM objects.

    ``created_at`` is in UTC.

    Raises
    ------
    NotFoundError
        No such patient.
    """
    with catalog.reading() as conn:
        row = conn.execute(_PATIENT_INFO, patient_params(identifier)).first()
    if row is None:
        raise NotFoundError(
            "unknown patient: register it first with `rasterserver patient add`"
        )
    return PatientInfo._make(row)
