"""The archive service: patients, stations, calibrations, ingest, listing and verification.

The CLI and the HTTP API both call this module; neither touches SQL or HDF5 directly.

Ingest is ordered so that a crash at any point leaves the archive explainable: every frame is
decoded and validated first (nothing is written for bad input), then the acquisition's HDF5
file is written under a temporary name, fsynced and renamed, and only then is the SQL row
committed. So there is never a row without its complete file; a crash between rename and
commit leaves an *orphaned* file, and a crash before the rename a *temporary* file, both of
which ``verify`` reports and explains.

Patient data (identifier, name, birth date) is never written to the log; acquisitions are
logged by their uid only.
"""

from __future__ import annotations

import datetime as dt
import functools
import hashlib
import logging
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from sqlalchemy import Connection, Engine, Integer, Select, bindparam, func, select
from sqlalchemy.exc import IntegrityError as SQLIntegrityError
from sqlalchemy.orm import Session, selectinload

from rasterserver.catalog.catalog import Catalog
from rasterserver.catalog.lookup import patient_id_of, stored_name
from rasterserver.catalog.models import (
    ACQUISITION_KINDS,
    FRAME_ROLES,
    SEXES,
    Acquisition,
    Calibration,
    Frame,
    IngestKey,
    Patient,
    Raster,
    Station,
    Visit,
)
from rasterserver.config import Settings
from rasterserver.errors import ConflictError, InputError, NotFoundError
from rasterserver.frame_fit import check_frames_fit
from rasterserver.hashing import canonical_json_sha256
from rasterserver.identifiers import PATIENT_MAX, check_name, lookup_key
from rasterserver.integrity import Problem as Problem  # re-exported
from rasterserver.integrity import Progress, VerifyReport, verify_raw
from rasterserver.store.raw import FrameToWrite, RawStore, StoredFrame
from rasterserver.times import require_zone

# rasterserver.documents (pydantic models built at import) and rasterserver.imageio (OpenCV)
# are imported by the methods that check documents and decode frames: `rasterserver list`
# and the other readers of the catalogue start without them.

if TYPE_CHECKING:
    from rasterserver.repair import RepairReport

log = logging.getLogger(__name__)

#: Called with the name of each ingest step as it completes; the crash tests kill the
#: process from here. Steps: those of :class:`RawStore` and ``"committed"``.
CrashHook = Callable[[str], None]


@dataclass(frozen=True)
class FrameSource:
    """One frame to ingest.

    Attributes
    ----------
    data : Path, bytes or numpy.ndarray
        A file (PNG, TIFF, NPY, raw), its bytes (an upload), or an array already in memory.
    role : str
        What the frame shows: ``raster`` (projector on, a patient), ``projector-off``,
        ``projector-on`` (calibration frames), ``dark`` or ``other``.
    name : str
        File name used in messages and to tell the format of ``bytes``; defaults to the
        file's name.
    """

    data: Path | bytes | np.ndarray
    role: str = "raster"
    name: str = ""


@dataclass(frozen=True)
class AcquisitionSpec:
    """One acquisition to ingest with :meth:`Archive.ingest_many`.

    The attributes mean what the keyword arguments of :meth:`Archive.ingest` mean.
    """

    frames: Sequence[FrameSource]
    patient: str | None
    kind: str = "patient"
    visit_date: dt.date | None = None
    station: str | None = None
    calibration_version: int | None = None
    acquired_at: dt.datetime | None = None
    operator: str = ""
    notes: str = ""
    #: with ``source``: the idempotency key of :meth:`Archive.ingest_once`
    idempotency_key: str | None = None
    source: str = ""


# Named tuples rather than frozen dataclasses: a list of a hundred acquisitions builds a
# few hundred of them per request, and a frozen dataclass costs several times more to make.
class FrameInfo(NamedTuple):
    """A frame's catalogue entry, as :meth:`Archive.find` and :meth:`Archive.info` give it."""

    index: int
    role: str
    height: int
    width: int
    dtype: str
    sha256: str


class PatientInfo(NamedTuple):
    """A patient's catalogue entry read without ORM objects (:meth:`Archive.patient_info`)."""

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


@dataclass(frozen=True)
class _References:
    patient_id: int | None
    station_id: int | None
    calibration_id: int | None


def _check_spec(spec: AcquisitionSpec) -> None:
    """Refuse an acquisition whose own fields are inconsistent (before any lookup)."""
    if not spec.frames:
        raise InputError("an acquisition needs at least one frame")
    if spec.kind not in ACQUISITION_KINDS:
        raise InputError(f"kind must be one of {', '.join(ACQUISITION_KINDS)}")
    for source in spec.frames:
        if source.role not in FRAME_ROLES:
            raise InputError(
                f"{source.name or 'frame'}: unknown role {source.role!r} "
                f"(one of {', '.join(FRAME_ROLES)})"
            )
    if spec.kind == "patient" and not spec.patient:
        raise InputError("a patient acquisition needs --patient")
    if spec.acquired_at is not None:
        require_zone(spec.acquired_at, "acquisition time")


def _check_range(since: dt.datetime | None, until: dt.datetime | None) -> None:
    """Refuse listing bounds without a time zone (their meaning would depend on the backend)."""
    for value, what in ((since, "since"), (until, "until")):
        if value is not None:
            require_zone(value, what)


# The statements of find() and info() are built once, with bound parameters: building a
# SQLAlchemy statement costs more Python than running it on a page of a hundred rows.
_INFO_COLUMNS = (
    Acquisition.id, Acquisition.uid, Acquisition.kind, Acquisition.patient_id,
    Patient.identifier, Acquisition.station_id, Acquisition.calibration_id,
    Acquisition.acquired_at, Acquisition.operator, Acquisition.notes,
)
_FRAME_COLUMNS = (Frame.index, Frame.role, Frame.height, Frame.width, Frame.dtype, Frame.sha256)


def _patient_params(identifier: str) -> dict[str, str]:
    """The bound values of :data:`_PATIENT_OF`."""
    return {"identifier": identifier, "identifier_key": lookup_key(identifier)}


_PATIENT_OF = patient_id_of(bindparam("identifier"), bindparam("identifier_key"))
_PATIENT_ID = select(Patient.id).where(Patient.id == _PATIENT_OF)
_PATIENT_INFO = select(Patient.id, Patient.identifier, Patient.name, Patient.birth_date,
                       Patient.sex, Patient.created_at).where(Patient.id == _PATIENT_OF)


def _with_frames(page: Select[Any]) -> Select[Any]:
    """``page`` (the info columns, ordered) joined to its frames, in the same order."""
    sub = page.subquery()
    return (select(sub, *_FRAME_COLUMNS)
            .outerjoin(Frame, Frame.acquisition_id == sub.c.id)
            .order_by(sub.c.acquired_at.desc(), sub.c.id.desc(), Frame.index))


@functools.cache
def _find_statement(patient: bool, since: bool, until: bool, kind: bool) -> Select[Any]:
    """The statement of :meth:`Archive.find` for one combination of filters."""
    page = select(*_INFO_COLUMNS).outerjoin(Patient, Patient.id == Acquisition.patient_id)
    if patient:  # by identifier, in the same query: no round trip to look up the id first
        page = page.where(Acquisition.patient_id == _PATIENT_OF)
    if since:
        page = page.where(Acquisition.acquired_at >= bindparam("since"))
    if until:
        page = page.where(Acquisition.acquired_at < bindparam("until"))
    if kind:
        page = page.where(Acquisition.kind == bindparam("kind"))
    page = (page.order_by(Acquisition.acquired_at.desc(), Acquisition.id.desc())
            .limit(bindparam("limit", type_=Integer)).offset(bindparam("offset", type_=Integer)))
    return _with_frames(page)


_INFO_BY_UID = _with_frames(
    select(*_INFO_COLUMNS).outerjoin(Patient, Patient.id == Acquisition.patient_id)
    .where(Acquisition.uid == bindparam("uid")).order_by(Acquisition.acquired_at.desc(),
                                                         Acquisition.id.desc()))


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


def _fingerprint(spec: AcquisitionSpec, shape: tuple[int, int] | None, dtype: str | None,
                 convert_color: bool) -> str:
    """SHA-256 of an upload: every frame's bytes and role, and the metadata (not file names,
    which a retry may change)."""
    digest = hashlib.sha256()
    for src in spec.frames:
        data = src.data
        if isinstance(data, np.ndarray):
            digest.update(f"array {data.dtype.str} {data.shape}".encode())
            data = np.ascontiguousarray(data).tobytes()
        elif isinstance(data, Path):
            data = data.read_bytes()
        digest.update(hashlib.sha256(data).digest() + src.role.encode() + b"\0")
    when = spec.acquired_at.isoformat() if spec.acquired_at else None
    day = spec.visit_date.isoformat() if spec.visit_date else None
    digest.update(canonical_json_sha256([
        spec.patient, spec.kind, day, spec.station, spec.calibration_version, when,
        spec.operator, spec.notes, list(shape) if shape else None, dtype, convert_color,
    ]).encode())
    return digest.hexdigest()


class Archive:
    """The archive at ``settings.archive`` with its catalogue at ``settings.database_url``.

    Parameters
    ----------
    settings : Settings
        Where the archive and the catalogue are.
    crash_hook : CrashHook, optional
        Test hook called after each durable ingest step.
    check_schema : bool, default True
        Refuse to work on a catalogue that is not migrated to the current revision.
    connections : int, optional
        Catalogue connections kept open for reuse (see
        :class:`~rasterserver.catalog.catalog.Catalog`).
    catalog : Catalog, optional
        An open catalogue to use (and leave open) instead of opening one;
        ``check_schema`` and ``connections`` are then the catalogue's business.
    """

    def __init__(
        self,
        settings: Settings,
        *,
        crash_hook: CrashHook | None = None,
        check_schema: bool = True,
        connections: int | None = None,
        catalog: Catalog | None = None,
    ) -> None:
        self.settings = settings
        #: The catalogue (engine, sessions, reads, the write lock); closed with the archive
        #: unless it was given.
        self.catalog = catalog if catalog is not None else Catalog(
            settings.database_url, check_schema=check_schema, connections=connections)
        self._owns_catalog = catalog is None
        self.engine: Engine = self.catalog.engine
        #: Taken by the catalogue's frequent writers (ingest, the audit trail): see WriteLock.
        self.write_lock = self.catalog.write_lock
        self._crash_hook = crash_hook
        self.raw = RawStore(settings.archive, crash_hook=crash_hook)

    def reading(self) -> Connection:
        """A catalogue connection for *one* read-only statement, outside a transaction.

        See :meth:`rasterserver.catalog.catalog.Catalog.reading`.
        """
        return self.catalog.reading()

    @classmethod
    def create(cls, settings: Settings, **kwargs: Any) -> Archive:
        """Open the archive, first migrating its catalogue to the newest schema."""
        from rasterserver.pseudonym_key import key_file

        Catalog.create(settings.database_url, key_file=key_file(settings),
                       check_schema=False).close()
        return cls(settings, **kwargs)

    def close(self) -> None:
        """Release the catalogue's connections (if the archive opened the catalogue)."""
        if self._owns_catalog:
            self.catalog.close()

    def __enter__(self) -> Archive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def session(self) -> AbstractContextManager[Session]:
        """A catalogue session committed on success and rolled back on any error."""
        return self.catalog.session()

    # -- patients, stations, rasters, calibrations ----------------------------------------

    def add_patient(
        self,
        identifier: str,
        *,
        name: str = "",
        birth_date: dt.date | None = None,
        sex: str = "unknown",
    ) -> Patient:
        """Register a patient under the site's identifier.

        The identifier follows :mod:`rasterserver.identifiers` (stored NFC; printable, no
        ``/``, at most 64 characters) and must differ from every registered one by more than
        case or look-alike characters.

        Raises
        ------
        InputError
            An identifier that breaks the rules, or an unknown sex.
        ConflictError
            The identifier, or a look-alike of it, is already taken.
        """
        identifier = check_name(identifier, "a patient identifier", max_length=PATIENT_MAX)
        if sex not in SEXES:
            raise InputError(f"sex must be one of {', '.join(SEXES)}")
        patient = Patient(identifier=identifier, identifier_key=lookup_key(identifier),
                          name=name, birth_date=birth_date, sex=sex)
        try:
            with self.session() as session:
                session.add(patient)
        except SQLIntegrityError:
            raise ConflictError("a patient with this identifier, or one that differs only in "
                                "case or look-alike characters, exists already") from None
        return patient

    def patient(self, identifier: str, session: Session | None = None) -> Patient:
        """Return the patient with ``identifier`` or raise :class:`NotFoundError`.

        The identifier as registered, or failing that one that differs from it only in case
        or look-alike characters (:func:`~rasterserver.catalog.lookup.patient_id_of`).
        """
        with self._maybe_session(session) as s:
            found = s.scalar(select(Patient).where(Patient.id == _PATIENT_OF),
                             _patient_params(identifier))
        if found is None:
            raise NotFoundError(
                "unknown patient: register it first with `rasterserver patient add`"
            )
        return found

    def patient_info(self, identifier: str) -> PatientInfo:
        """The catalogue entry of the patient with ``identifier``, read without ORM objects.

        ``created_at`` is in UTC.

        Raises
        ------
        NotFoundError
            No such patient.
        """
        with self.reading() as conn:
            row = conn.execute(_PATIENT_INFO, _patient_params(identifier)).first()
        if row is None:
            raise NotFoundError(
                "unknown patient: register it first with `rasterserver patient add`"
            )
        return PatientInfo._make(row)

    def patients(self, *, limit: int = 100, offset: int = 0) -> list[Patient]:
        """List patients by identifier."""
        with self.session() as s:
            return list(
                s.scalars(select(Patient).order_by(Patient.identifier).limit(limit).offset(offset))
            )

    def add_station(self, name: str, *, description: str = "") -> Station:
        """Register an acquisition station (a camera and projector set-up).

        The name follows :mod:`rasterserver.identifiers` and must differ from every other
        station's by more than case or look-alike characters.
        """
        name = check_name(name, "a station name")
        station = Station(name=name, description=description)
        try:
            with self.session() as session:
                if (other := stored_name(session, Station.name, name, exact=False)):
                    raise ConflictError(f"station {other!r} exists already")
                session.add(station)
        except SQLIntegrityError:
            raise ConflictError(f"station {name!r} exists already") from None
        return station

    def station(self, name: str, session: Session | None = None) -> Station:
        """Return the station called ``name`` (or, failing that, a name that differs only in
        case or look-alike characters) or raise :class:`NotFoundError`."""
        with self._maybe_session(session) as s:
            named = stored_name(s, Station.name, name)
            found = None if named is None else s.scalar(select(Station)
                                                        .where(Station.name == named))
        if found is None:
            raise NotFoundError(f"unknown station {name!r}")
        return found

    def stations(self) -> list[Station]:
        """List every station by name."""
        with self.session() as s:
            return list(s.scalars(select(Station).order_by(Station.name)))

    def add_raster(
        self, name: str, definition: dict[str, Any], *, source: str = "raster definition"
    ) -> Raster:
        """Store a raster diapositive definition; the same definition is stored once.

        Returns the existing row when an identical definition is stored under the same name.
        The definition is checked first (:func:`rasterserver.documents.raster_from_document`;
        ``source`` names it in the message).
        """
        from rasterserver.documents import raster_from_document

        name = check_name(name, "a raster name")
        raster_from_document(definition, source=source)
        digest = canonical_json_sha256(definition)
        with self.session() as s:
            same = s.scalar(select(Raster).where(Raster.sha256 == digest))
            if same is not None:
                if same.name != name:
                    raise ConflictError(
                        f"this raster definition is stored already as {same.name!r}"
                    )
                return same
            if (other := stored_name(s, Raster.name, name, exact=False)):
                raise ConflictError(f"another raster is called {other!r}")
            raster = Raster(name=name, definition=definition, sha256=digest)
            s.add(raster)
            try:
                s.flush()
            except SQLIntegrityError:
                raise ConflictError(f"another raster is called {name!r}") from None
        return raster

    def raster(self, name: str) -> Raster:
        """Return the raster called ``name`` (as :meth:`station`) or raise
        :class:`NotFoundError`."""
        with self.session() as s:
            named = stored_name(s, Raster.name, name)
            found = None if named is None else s.scalar(select(Raster)
                                                        .where(Raster.name == named))
        if found is None:
            raise NotFoundError(f"unknown raster {name!r}")
        return found

    def add_calibration(
        self,
        station: str,
        parameters: dict[str, Any],
        *,
        residuals: dict[str, Any] | None = None,
        raster: str | None = None,
        valid_from: dt.datetime | None = None,
        source_acquisition: str | None = None,
        notes: str = "",
        source: str = "calibration",
    ) -> Calibration:
        """Store a new calibration version of ``station``.

        Versions count up from 1 per station; a stored calibration is never changed.

        Parameters
        ----------
        station : str
            Station name.
        parameters : dict
            The calibration document (``rasterserver.calibration/1``).
        residuals : dict, optional
            Residuals of the adjustment (per point, per line, rms).
        raster : str, optional
            Name of the raster diapositive the calibration was made with.
        valid_from : datetime, optional
            From when the calibration applies; now by default.
        source_acquisition : str, optional
            uid of the acquisition holding the control-point frames.
        notes : str
            Free text.
        source : str
            How a refusal names the document (a file name).

        Returns
        -------
        Calibration

        Raises
        ------
        InputError
            The document is refused (:func:`rasterserver.documents.calibration_from_document`).
        """
        from rasterserver.documents import calibration_from_document

        calibration_from_document(parameters, source=source)
        if valid_from is not None:
            require_zone(valid_from, "valid from")
        with self.session() as s:
            st = self.station(station, s)
            raster_row = None
            if raster is not None:
                named = stored_name(s, Raster.name, raster)
                raster_row = None if named is None else s.scalar(select(Raster)
                                                                 .where(Raster.name == named))
                if raster_row is None:
                    raise NotFoundError(f"unknown raster {raster!r}")
            source_id = None
            if source_acquisition is not None:
                source_id = self._acquisition_row(s, source_acquisition).id
            version = (
                s.scalar(
                    select(func.max(Calibration.version)).where(Calibration.station_id == st.id)
                )
                or 0
            ) + 1
            cal = Calibration(
                station_id=st.id,
                version=version,
                raster_id=raster_row.id if raster_row else None,
                parameters=parameters,
                residuals=residuals or {},
                sha256=canonical_json_sha256(parameters),
                valid_from=valid_from or dt.datetime.now(dt.UTC),
                source_acquisition_id=source_id,
                notes=notes,
            )
            s.add(cal)
        return cal

    def calibration(
        self, station: str, version: int | None = None, session: Session | None = None
    ) -> Calibration:
        """Return a calibration of ``station``: the given version, or the newest one."""
        with self._maybe_session(session) as s:
            st = self.station(station, s)
            query = select(Calibration).where(Calibration.station_id == st.id)
            if version is None:
                query = query.order_by(Calibration.version.desc()).limit(1)
            else:
                query = query.where(Calibration.version == version)
            found = s.scalar(query)
        if found is None:
            which = "no calibration" if version is None else f"no calibration version {version}"
            raise NotFoundError(f"station {station!r} has {which}")
        return found

    def calibration_at(
        self, station: str, when: dt.datetime, session: Session | None = None
    ) -> Calibration:
        """Return the calibration of ``station`` valid at ``when``.

        That is the newest version whose ``valid_from`` is not after ``when``: an acquisition
        is reconstructed with the calibration in force when it was taken, even if the
        station has been recalibrated since.

        Raises
        ------
        NotFoundError
            No calibration of the station was valid yet at ``when``.
        """
        with self._maybe_session(session) as s:
            st = self.station(station, s)
            found = s.scalar(
                select(Calibration)
                .where(Calibration.station_id == st.id, Calibration.valid_from <= when)
                .order_by(Calibration.valid_from.desc(), Calibration.version.desc())
                .limit(1)
            )
        if found is None:
            raise NotFoundError(
                f"station {station!r} has no calibration valid at "
                f"{when.astimezone(dt.UTC):%Y-%m-%d %H:%M} UTC; "
                "give a calibration version explicitly"
            )
        return found

    def calibrations(self, station: str) -> list[Calibration]:
        """Return every calibration of ``station``, oldest version first."""
        with self.session() as s:
            st = self.station(station, s)
            return list(
                s.scalars(
                    select(Calibration)
                    .where(Calibration.station_id == st.id)
                    .order_by(Calibration.version)
                )
            )

    # -- ingest -----------------------------------------------------------------------------

    def ingest(
        self,
        frames: Sequence[FrameSource],
        *,
        patient: str | None,
        kind: str = "patient",
        visit_date: dt.date | None = None,
        station: str | None = None,
        calibration_version: int | None = None,
        acquired_at: dt.datetime | None = None,
        operator: str = "",
        notes: str = "",
        shape: tuple[int, int] | None = None,
        dtype: str | None = None,
        convert_color: bool = False,
    ) -> Acquisition:
        """Validate and store one acquisition of one or several frames.

        Nothing is stored unless every frame is valid and every reference exists.

        Parameters
        ----------
        frames : sequence of FrameSource
            The frames, stored in this order with indices 0, 1, ...
        patient : str or None
            The patient's identifier; required for ``kind="patient"``.
        kind : {"patient", "calibration", "test"}
            What was recorded.
        visit_date : date, optional
            The visit it belongs to (created on first use); defaults to the acquisition date.
        station : str, optional
            Station name; required to attach a calibration.
        calibration_version : int, optional
            Calibration version of ``station``; by default the newest one, if any.
        acquired_at : datetime, optional
            When the frames were taken, with its time zone (stored in UTC); now by default.
            The visit is the day at that time's own offset (the clinic's day).
        operator, notes : str
            Free text.
        shape, dtype : optional
            Shape and dtype of raw-bytes frames (and the expected ones for other formats).
        convert_color : bool
            Convert colour images to grey instead of refusing them.

        Returns
        -------
        Acquisition
            The committed row, with its frames.
        """
        spec = AcquisitionSpec(
            frames=tuple(frames),
            patient=patient,
            kind=kind,
            visit_date=visit_date,
            station=station,
            calibration_version=calibration_version,
            acquired_at=acquired_at,
            operator=operator,
            notes=notes,
        )
        return self.ingest_many(
            [spec], shape=shape, dtype=dtype, convert_color=convert_color
        )[0]

    def ingest_once(
        self,
        frames: Sequence[FrameSource],
        *,
        source: str,
        key: str,
        patient: str | None,
        shape: tuple[int, int] | None = None,
        dtype: str | None = None,
        convert_color: bool = False,
        **metadata: Any,
    ) -> tuple[Acquisition, bool]:
        """:meth:`ingest` under an idempotency key: a retry does not store twice.

        A station that lost the answer to an upload (a timeout, a dropped connection) sends
        it again under the same key; the archive then returns what the first attempt stored.
        Keys are scoped by ``source`` (the uploading account); the key is stored with the
        acquisition in one transaction, so of two concurrent attempts only one commits.

        Parameters
        ----------
        frames, patient, shape, dtype, convert_color, **metadata
            As for :meth:`ingest`.
        source : str
            Who is uploading (the account name; ``cli`` for the command line).
        key : str
            The client's key for this upload, 1 to 100 characters.

        Returns
        -------
        (Acquisition, bool)
            The acquisition, and whether an earlier call with this key had stored it.

        Raises
        ------
        ConflictError
            The key was used before for a different upload (other frames or metadata).
        """
        if not key or len(key) > 100 or not source or len(source) > 100:
            raise InputError("an idempotency key has 1 to 100 characters")
        spec = AcquisitionSpec(frames=tuple(frames), patient=patient, idempotency_key=key,
                               source=source, **metadata)
        fingerprint = _fingerprint(spec, shape, dtype, convert_color)
        if (earlier := self._keyed(source, key, fingerprint)) is not None:
            return earlier, True
        try:
            return self.ingest_many([spec], shape=shape, dtype=dtype,
                                    convert_color=convert_color)[0], False
        except SQLIntegrityError:
            # lost a race with a concurrent attempt under the same key, which committed
            if (earlier := self._keyed(source, key, fingerprint)) is not None:
                return earlier, True
            raise

    def _keyed(self, source: str, key: str, fingerprint: str) -> Acquisition | None:
        with self.session() as s:
            row = s.get(IngestKey, (source, key))
            if row is None:
                return None
            if row.request_sha256 != fingerprint:
                raise ConflictError(
                    f"idempotency key {key!r} was used before for a different upload")
            uid = s.scalar(select(Acquisition.uid).where(Acquisition.id == row.acquisition_id))
        return self.acquisition(uid)

    def ingest_many(
        self,
        specs: Sequence[AcquisitionSpec],
        *,
        shape: tuple[int, int] | None = None,
        dtype: str | None = None,
        convert_color: bool = False,
        workers: int = 1,
    ) -> list[Acquisition]:
        """Validate and store several acquisitions at once, all or none.

        Files are written (and fsynced) by ``workers`` threads, so the disk's flushes
        overlap, and all rows are committed in one transaction: the way to import a
        backlog quickly without giving up durability.

        Parameters
        ----------
        specs : sequence of AcquisitionSpec
            The acquisitions.
        shape, dtype, convert_color
            As for :meth:`ingest`, applied to every frame.
        workers : int
            Threads writing files.

        Returns
        -------
        list of Acquisition
            The committed rows, in the order of ``specs``.
        """
        if not specs:
            return []
        # in the server's zone, so that the default visit is the local day (stored in UTC)
        now = dt.datetime.now().astimezone()
        for spec in specs:
            _check_spec(spec)
        # References first: an unknown patient or calibration stores nothing.
        with self.session() as s:
            refs = [self._references(s, spec, now) for spec in specs]
        decoded = [
            [self._decode(src, shape=shape, dtype=dtype, convert_color=convert_color)
             for src in spec.frames]
            for spec in specs
        ]
        check_frames_fit(self, specs, [ref.calibration_id for ref in refs], decoded)
        uids = [uuid.uuid4().hex for _ in specs]

        def write(i: int) -> list[StoredFrame]:
            return self.raw.write(
                uids[i],
                [
                    FrameToWrite(index=k, role=src.role, array=arr)
                    for k, (src, arr) in enumerate(zip(specs[i].frames, decoded[i], strict=True))
                ],
            )

        try:
            if workers > 1 and len(specs) > 1:
                with ThreadPoolExecutor(max_workers=workers) as pool:
                    stored = list(pool.map(write, range(len(specs))))
            else:
                stored = [write(i) for i in range(len(specs))]
            fingerprints = [_fingerprint(spec, shape, dtype, convert_color)
                            if spec.idempotency_key is not None else "" for spec in specs]
            acquisitions = self._commit_rows(specs, refs, uids, stored, fingerprints, now)
        except BaseException:
            # No row made it: the files would only be orphans, so take them back. They were
            # never part of the archive, so this is no breach of write-once.
            for uid in uids:
                self.raw.path_for(uid).unlink(missing_ok=True)
            raise
        if self._crash_hook is not None:
            self._crash_hook("committed")
        for acq in acquisitions:
            log.info("ingested acquisition %s (%d frames)", acq.uid, len(acq.frames))
        return acquisitions

    def _references(self, s: Session, spec: AcquisitionSpec, now: dt.datetime) -> _References:
        patient_row = self.patient(spec.patient, s) if spec.patient else None
        station_row = self.station(spec.station, s) if spec.station else None
        cal_row = None
        if spec.calibration_version is not None and station_row is None:
            raise InputError("a calibration version needs --station")
        if station_row is not None:
            has_any = s.scalar(
                select(func.count()).where(Calibration.station_id == station_row.id)
            )
            if spec.calibration_version is not None:
                cal_row = self.calibration(station_row.name, spec.calibration_version, s)
            elif has_any:
                cal_row = self.calibration_at(station_row.name, spec.acquired_at or now, s)
        return _References(
            patient_id=patient_row.id if patient_row else None,
            station_id=station_row.id if station_row else None,
            calibration_id=cal_row.id if cal_row else None,
        )

    def _commit_rows(
        self,
        specs: Sequence[AcquisitionSpec],
        refs: Sequence[_References],
        uids: Sequence[str],
        stored: Sequence[list[StoredFrame]],
        fingerprints: Sequence[str],
        now: dt.datetime,
    ) -> list[Acquisition]:
        rows = []
        with self.write_lock(), self.session() as s:
            for spec, ref, uid, frames, fingerprint in zip(specs, refs, uids, stored,
                                                           fingerprints, strict=True):
                acquired_at = spec.acquired_at or now
                visit_id = None
                if ref.patient_id is not None:
                    day = spec.visit_date or acquired_at.date()
                    visit_id = self._visit(s, ref.patient_id, day).id
                acq = Acquisition(
                    uid=uid,
                    kind=spec.kind,
                    patient_id=ref.patient_id,
                    visit_id=visit_id,
                    station_id=ref.station_id,
                    calibration_id=ref.calibration_id,
                    acquired_at=acquired_at,
                    operator=spec.operator,
                    notes=spec.notes,
                )
                acq.frames = [
                    Frame(
                        index=f.index,
                        role=f.role,
                        height=f.shape[0],
                        width=f.shape[1],
                        dtype=f.dtype,
                        sha256=f.sha256,
                        store_path=f.path,
                        dataset=f.dataset,
                    )
                    for f in frames
                ]
                s.add(acq)
                rows.append(acq)
                if spec.idempotency_key is not None:
                    s.flush()  # the acquisition's id, for the key
                    s.add(IngestKey(source=spec.source, key=spec.idempotency_key,
                                    acquisition_id=acq.id,
                                    request_sha256=fingerprint))
        return rows

    def _decode(
        self,
        source: FrameSource,
        *,
        shape: tuple[int, int] | None,
        dtype: str | None,
        convert_color: bool,
    ) -> np.ndarray:
        from rasterserver.imageio import decode_frame_bytes, read_frame

        limit = self.settings.max_frame_bytes
        if isinstance(source.data, np.ndarray):
            return _validate_array(source.data, source.name or "array", limit)
        if isinstance(source.data, bytes):
            return decode_frame_bytes(
                source.data,
                name=source.name or "upload",
                shape=shape,
                dtype=dtype,
                convert_color=convert_color,
                max_bytes=limit,
            )
        return read_frame(
            Path(source.data),
            shape=shape,
            dtype=dtype,
            convert_color=convert_color,
            max_bytes=limit,
        )

    @staticmethod
    def _visit(session: Session, patient_id: int, day: dt.date) -> Visit:
        """Return the patient's visit on ``day``, creating it if needed.

        Two stations ingesting for the same patient on the same day race to create the
        visit; the loser's insert fails on the unique key inside a savepoint and it takes
        the winner's row instead of failing the whole ingest.
        """
        query = select(Visit).where(Visit.patient_id == patient_id, Visit.visit_date == day)
        visit = session.scalar(query)
        if visit is not None:
            return visit
        try:
            with session.begin_nested():
                visit = Visit(patient_id=patient_id, visit_date=day)
                session.add(visit)
        except SQLIntegrityError:
            visit = session.scalar(query)
            if visit is None:  # pragma: no cover - the unique key failed for another reason
                raise
        return visit

    # -- reading ------------------------------------------------------------------------------

    def acquisitions(
        self,
        *,
        patient: str | None = None,
        since: dt.datetime | None = None,
        until: dt.datetime | None = None,
        kind: str | None = None,
        limit: int = 100,
        offset: int = 0,
    ) -> list[Acquisition]:
        """List acquisitions, newest first, optionally of one patient and in a time range.

        ``since`` is inclusive and ``until`` exclusive.
        """
        query = select(Acquisition).options(
            selectinload(Acquisition.frames), selectinload(Acquisition.patient)
        )
        with self.session() as s:
            query = self._newest_first(s, query, patient, since, until, kind)
            return list(s.scalars(query.limit(limit).offset(offset)))

    def _newest_first(
        self,
        s: Session,
        query: Select[Any],
        patient: str | None,
        since: dt.datetime | None,
        until: dt.datetime | None,
        kind: str | None,
    ) -> Select[Any]:
        """Apply the listing filters (``since`` inclusive, ``until`` exclusive) and order."""
        _check_range(since, until)
        if patient is not None:
            query = query.where(Acquisition.patient_id == self.patient(patient, s).id)
        if since is not None:
            query = query.where(Acquisition.acquired_at >= since)
        if until is not None:
            query = query.where(Acquisition.acquired_at < until)
        if kind is not None:
            query = query.where(Acquisition.kind == kind)
        return query.order_by(Acquisition.acquired_at.desc(), Acquisition.id.desc())

    def find(
        self,
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
        Filters as for :meth:`acquisitions`.
        """
        _check_range(since, until)
        params: dict[str, Any] = {"identifier": patient, "since": since, "until": until,
                                  "kind": kind, "limit": limit, "offset": offset}
        if patient is not None:
            params["identifier_key"] = lookup_key(patient)
        query = _find_statement(*(params[k] is not None
                                  for k in ("identifier", "since", "until", "kind")))
        with self.reading() as conn:
            found = _infos(conn.execute(query, params))
            # an empty page of an unknown patient is an error; one more query tells which
            if not found and patient is not None and conn.execute(
                    _PATIENT_ID, _patient_params(patient)).first() is None:
                raise NotFoundError(
                    "unknown patient: register it first with `rasterserver patient add`")
        return found

    def info(self, uid: str) -> AcquisitionInfo:
        """The catalogue entry of acquisition ``uid`` (see :meth:`find`).

        Raises
        ------
        NotFoundError
            No such acquisition.
        """
        with self.reading() as conn:
            found = _infos(conn.execute(_INFO_BY_UID, {"uid": uid}))
        if not found:
            raise NotFoundError(f"unknown acquisition {uid}")
        return found[0]

    def acquisition(self, uid: str) -> Acquisition:
        """Return the acquisition ``uid`` with its frames, or raise :class:`NotFoundError`."""
        with self.session() as s:
            return self._acquisition_row(s, uid)

    @staticmethod
    def _acquisition_row(session: Session, uid: str) -> Acquisition:
        found = session.scalar(
            select(Acquisition)
            .options(selectinload(Acquisition.frames), selectinload(Acquisition.patient))
            .where(Acquisition.uid == uid)
        )
        if found is None:
            raise NotFoundError(f"unknown acquisition {uid}")
        return found

    def read_frame(self, uid: str, index: int = 0) -> np.ndarray:
        """Return frame ``index`` of acquisition ``uid`` as a read-only array."""
        acq = self.acquisition(uid)
        if not any(f.index == index for f in acq.frames):
            raise NotFoundError(f"acquisition {uid} has no frame {index}")
        return self.raw.read(uid, index)

    # -- verification -------------------------------------------------------------------------

    def verify(self, *, progress: Progress | None = None) -> VerifyReport:
        """Re-hash every stored frame and compare files with catalogue rows.

        See :func:`rasterserver.integrity.verify_raw`.

        Returns
        -------
        VerifyReport
            Missing, corrupt, orphaned and temporary files, with explanations.
        """
        return verify_raw(self.catalog, self.raw, progress=progress)

    def repair(
        self,
        report: VerifyReport,
        *,
        dry_run: bool = False,
        min_age: dt.timedelta | None = None,
        progress: Progress | None = None,
    ) -> RepairReport:
        """Clean up the harmless leftovers ``report`` lists, never losing data.

        Temporary files (never published) are deleted; orphaned files (complete, without a
        catalogue row) are moved into ``<archive>/quarantine/<date>/`` with a manifest; stray
        files are left alone; missing, corrupt and unreadable files are not touched and are
        reported as needing a person. Each file is checked again right before anything is
        done to it. See :mod:`rasterserver.repair` for the rules and why they are safe.

        Parameters
        ----------
        report : VerifyReport
            What :meth:`verify` (and the pipeline's ``verify``) found.
        dry_run : bool, default False
            Change nothing; the result says what would be done.
        min_age : datetime.timedelta, optional
            Leave files younger than this (default one hour) for a later run: a writer may
            still be at work on them.
        progress : Progress, optional
            Called with (done, total) after each problem.

        Returns
        -------
        RepairReport

        Raises
        ------
        ConflictError
            Another repair of this archive is running.
        """
        # Imported here: the repair module needs this one's types, and most uses of the
        # archive (the HTTP server) never repair.
        from rasterserver.repair import DEFAULT_MIN_AGE, repair

        return repair(self, report.problems, dry_run=dry_run, progress=progress,
                      min_age=DEFAULT_MIN_AGE if min_age is None else min_age)

    @contextmanager
    def _maybe_session(self, session: Session | None) -> Iterator[Session]:
        if session is not None:
            yield session
        else:
            with self.session() as s:
                yield s


def _validate_array(array: np.ndarray, name: str, limit: int) -> np.ndarray:
    """Apply the file decoder's checks to an in-memory array (one set of rules)."""
    from io import BytesIO

    from rasterserver.imageio import decode_frame_bytes

    buffer = BytesIO()
    np.save(buffer, np.asarray(array), allow_pickle=False)
    return decode_frame_bytes(buffer.getvalue(), name=f"{name}.npy", max_bytes=limit)
