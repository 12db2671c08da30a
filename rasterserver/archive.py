"""The archive service: patients, stations, rasters, calibrations, and the archive's verbs.

The CLI and the HTTP API both call this module; neither touches SQL or HDF5 directly. An
:class:`Archive` is the catalogue (:class:`~rasterserver.catalog.catalog.Catalog`) and the
raw store together; it delegates ingest to :mod:`rasterserver.ingest`, listing to
:mod:`rasterserver.catalog.listing`, verification to :mod:`rasterserver.integrity` and repair
to :mod:`rasterserver.repair`. Code that only needs the database takes a ``Catalog``.

Patient data (identifier, name, birth date) is never written to the log; acquisitions are
logged by their uid only.
"""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from typing import Any

import numpy as np
from sqlalchemy import Connection, Engine, Select, func, select
from sqlalchemy.exc import IntegrityError as SQLIntegrityError
from sqlalchemy.orm import Session, selectinload

from rasterserver import ingest as ingesting
from rasterserver.catalog import listing
from rasterserver.catalog.catalog import Catalog
from rasterserver.catalog.listing import PATIENT_OF, check_range, patient_params
from rasterserver.catalog.listing import AcquisitionInfo as AcquisitionInfo  # re-exported
from rasterserver.catalog.listing import FrameInfo as FrameInfo  # re-exported
from rasterserver.catalog.listing import PatientInfo as PatientInfo  # re-exported
from rasterserver.catalog.lookup import stored_name
from rasterserver.catalog.models import (
    SEXES,
    Acquisition,
    Calibration,
    Patient,
    Raster,
    Station,
)
from rasterserver.config import Settings
from rasterserver.errors import ConflictError, InputError, NotFoundError
from rasterserver.hashing import canonical_json_sha256
from rasterserver.identifiers import PATIENT_MAX, check_name, lookup_key
from rasterserver.ingest import AcquisitionSpec as AcquisitionSpec  # re-exported
from rasterserver.ingest import FrameSource as FrameSource  # re-exported
from rasterserver.integrity import Problem as Problem  # re-exported
from rasterserver.integrity import Progress, VerifyReport, verify_raw
from rasterserver.repair import DEFAULT_MIN_AGE, RepairReport, repair
from rasterserver.store.raw import RawStore
from rasterserver.times import require_zone

# rasterserver.documents (pydantic models built at import) and rasterserver.imageio (OpenCV)
# are imported by the methods that check documents and decode frames: `rasterserver list`
# and the other readers of the catalogue start without them.

log = logging.getLogger(__name__)

#: Called with the name of each ingest step as it completes; the crash tests kill the
#: process from here. Steps: those of :class:`RawStore` and ``"committed"``.
CrashHook = Callable[[str], None]


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
        #: Called after each durable ingest step (the crash tests).
        self.crash_hook = crash_hook
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
            found = s.scalar(select(Patient).where(Patient.id == PATIENT_OF),
                             patient_params(identifier))
        if found is None:
            raise NotFoundError(
                "unknown patient: register it first with `rasterserver patient add`"
            )
        return found

    def patient_info(self, identifier: str) -> PatientInfo:
        """The catalogue entry of a patient, read without ORM objects
        (:func:`rasterserver.catalog.listing.patient_info`)."""
        return listing.patient_info(self.catalog, identifier)

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

    # -- ingest (rasterserver.ingest) --------------------------------------------------------

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
        """Validate and store one acquisition: :func:`rasterserver.ingest.ingest`."""
        return ingesting.ingest(
            self, frames, patient=patient, kind=kind, visit_date=visit_date, station=station,
            calibration_version=calibration_version, acquired_at=acquired_at,
            operator=operator, notes=notes, shape=shape, dtype=dtype,
            convert_color=convert_color)

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
        """:meth:`ingest` under an idempotency key: :func:`rasterserver.ingest.ingest_once`."""
        return ingesting.ingest_once(self, frames, source=source, key=key, patient=patient,
                                  shape=shape, dtype=dtype, convert_color=convert_color,
                                  **metadata)

    def ingest_many(
        self,
        specs: Sequence[AcquisitionSpec],
        *,
        shape: tuple[int, int] | None = None,
        dtype: str | None = None,
        convert_color: bool = False,
        workers: int = 1,
    ) -> list[Acquisition]:
        """Store several acquisitions at once, all or none:
        :func:`rasterserver.ingest.ingest_many`."""
        return ingesting.ingest_many(self, specs, shape=shape, dtype=dtype,
                                  convert_color=convert_color, workers=workers)

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
        check_range(since, until)
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

        See :func:`rasterserver.catalog.listing.find`.
        """
        return listing.find(self.catalog, patient=patient, since=since, until=until,
                            kind=kind, limit=limit, offset=offset)

    def info(self, uid: str) -> AcquisitionInfo:
        """The catalogue entry of acquisition ``uid``: :func:`rasterserver.catalog.listing.info`.
        """
        return listing.info(self.catalog, uid)

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

        See :func:`rasterserver.repair.repair` for the rules and why they are safe.
        ``report`` is what :meth:`verify` (and the pipeline's ``verify``) found; ``min_age``
        defaults to :data:`rasterserver.repair.DEFAULT_MIN_AGE`.

        Raises
        ------
        ConflictError
            Another repair of this archive is running.
        """
        return repair(self, report.problems, dry_run=dry_run, progress=progress,
                      min_age=DEFAULT_MIN_AGE if min_age is None else min_age)

    @contextmanager
    def _maybe_session(self, session: Session | None) -> Iterator[Session]:
        if session is not None:
            yield session
        else:
            with self.session() as s:
                yield s
