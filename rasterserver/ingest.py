"""Ingest: validate frames and metadata, store them once, and the request both front ends send.

Ingest is ordered so that a crash at any point leaves the archive explainable: every frame is
decoded and validated first (nothing is written for bad input), then the acquisition's HDF5
file is written under a temporary name, fsynced and renamed, and only then is the SQL row
committed. So there is never a row without its complete file; a crash between rename and
commit leaves an *orphaned* file, and a crash before the rename a *temporary* file, both of
which ``verify`` reports and explains (:mod:`rasterserver.integrity`).

An upload may carry an idempotency key (:func:`ingest_once`): a retry of a lost answer then
returns what the first attempt stored instead of storing twice.

The command line and the HTTP route shape their input with
:mod:`rasterserver.ingest_request`.

Patient data are never written to the log; acquisitions are logged by their uid only.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import logging
import uuid
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError as SQLIntegrityError
from sqlalchemy.orm import Session

from rasterserver.catalog.models import (
    Acquisition,
    Calibration,
    Frame,
    IngestKey,
    Visit,
)
from rasterserver.catalog.vocabulary import ACQUISITION_KINDS, FRAME_ROLES
from rasterserver.errors import ConflictError, InputError
from rasterserver.frame_fit import check_frames_fit
from rasterserver.hashing import canonical_json_sha256
from rasterserver.store.raw import FrameToWrite, StoredFrame
from rasterserver.times import require_zone

# rasterserver.imageio (OpenCV) is imported by the function that decodes frames.

if TYPE_CHECKING:
    from rasterserver.archive import Archive

__all__ = [
    "AcquisitionSpec",
    "FrameSource",
    "ingest",
    "ingest_many",
    "ingest_once",
]

log = logging.getLogger(__name__)


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
    """One acquisition to ingest with :func:`ingest_many`.

    The attributes mean what the keyword arguments of :func:`ingest` mean.
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
    #: with ``source``: the idempotency key of :func:`ingest_once`
    idempotency_key: str | None = None
    source: str = ""


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


def ingest(
    archive: Archive,
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
    return ingest_many(archive,
        [spec], shape=shape, dtype=dtype, convert_color=convert_color
    )[0]


def ingest_once(
    archive: Archive,
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
    """:func:`ingest` under an idempotency key: a retry does not store twice.

    A station that lost the answer to an upload (a timeout, a dropped connection) sends
    it again under the same key; the archive then returns what the first attempt stored.
    Keys are scoped by ``source`` (the uploading account); the key is stored with the
    acquisition in one transaction, so of two concurrent attempts only one commits.

    Parameters
    ----------
    frames, patient, shape, dtype, convert_color, **metadata
        As for :func:`ingest`.
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
    if (earlier := _keyed(archive, source, key, fingerprint)) is not None:
        return earlier, True
    try:
        return ingest_many(archive, [spec], shape=shape, dtype=dtype,
                                convert_color=convert_color)[0], False
    except SQLIntegrityError:
        # lost a race with a concurrent attempt under the same key, which committed
        if (earlier := _keyed(archive, source, key, fingerprint)) is not None:
            return earlier, True
        raise


def _keyed(archive: Archive, source: str, key: str, fingerprint: str) -> Acquisition | None:
    with archive.session() as s:
        row = s.get(IngestKey, (source, key))
        if row is None:
            return None
        if row.request_sha256 != fingerprint:
            raise ConflictError(
                f"idempotency key {key!r} was used before for a different upload")
        uid = s.scalar(select(Acquisition.uid).where(Acquisition.id == row.acquisition_id))
    assert uid is not None  # the key's foreign key names an existing acquisition
    return archive.acquisition(uid)


def ingest_many(
    archive: Archive,
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
        As for :func:`ingest`, applied to every frame.
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
    with archive.session() as s:
        refs = [_references(archive, s, spec, now) for spec in specs]
    decoded = [
        [_decode(archive, src, shape=shape, dtype=dtype, convert_color=convert_color)
         for src in spec.frames]
        for spec in specs
    ]
    check_frames_fit(archive, specs, [ref.calibration_id for ref in refs], decoded)
    uids = [uuid.uuid4().hex for _ in specs]

    def write(i: int) -> list[StoredFrame]:
        return archive.raw.write(
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
        acquisitions = _commit_rows(archive, specs, refs, uids, stored, fingerprints, now)
    except BaseException:
        # No row made it: the files would only be orphans, so take them back. They were
        # never part of the archive, so this is no breach of write-once.
        for uid in uids:
            archive.raw.path_for(uid).unlink(missing_ok=True)
        raise
    if archive.crash_hook is not None:
        archive.crash_hook("committed")
    for acq in acquisitions:
        log.info("ingested acquisition %s (%d frames)", acq.uid, len(acq.frames))
    return acquisitions


def _references(archive: Archive, s: Session, spec: AcquisitionSpec,
                now: dt.datetime) -> _References:
    patient_row = archive.patient(spec.patient, s) if spec.patient else None
    station_row = archive.station(spec.station, s) if spec.station else None
    cal_row = None
    if spec.calibration_version is not None and station_row is None:
        raise InputError("a calibration version needs --station")
    if station_row is not None:
        has_any = s.scalar(
            select(func.count()).where(Calibration.station_id == station_row.id)
        )
        if spec.calibration_version is not None:
            cal_row = archive.calibration(station_row.name, spec.calibration_version, s)
        elif has_any:
            cal_row = archive.calibration_at(station_row.name, spec.acquired_at or now, s)
    return _References(
        patient_id=patient_row.id if patient_row else None,
        station_id=station_row.id if station_row else None,
        calibration_id=cal_row.id if cal_row else None,
    )


def _commit_rows(
    archive: Archive,
    specs: Sequence[AcquisitionSpec],
    refs: Sequence[_References],
    uids: Sequence[str],
    stored: Sequence[list[StoredFrame]],
    fingerprints: Sequence[str],
    now: dt.datetime,
) -> list[Acquisition]:
    rows = []
    with archive.write_lock(), archive.session() as s:
        for spec, ref, uid, frames, fingerprint in zip(specs, refs, uids, stored,
                                                       fingerprints, strict=True):
            acquired_at = spec.acquired_at or now
            visit_id = None
            if ref.patient_id is not None:
                day = spec.visit_date or acquired_at.date()
                visit_id = _visit(s, ref.patient_id, day).id
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
    archive: Archive,
    source: FrameSource,
    *,
    shape: tuple[int, int] | None,
    dtype: str | None,
    convert_color: bool,
) -> np.ndarray:
    from rasterserver.imageio import decode_frame_bytes, read_frame

    limit = archive.settings.max_frame_bytes
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


def _validate_array(array: np.ndarray, name: str, limit: int) -> np.ndarray:
    """Apply the file decoder's checks to an in-memory array (one set of rules)."""
    from io import BytesIO

    from rasterserver.imageio import decode_frame_bytes

    buffer = BytesIO()
    np.save(buffer, np.asarray(array), allow_pickle=False)
    return decode_frame_bytes(buffer.getvalue(), name=f"{name}.npy", max_bytes=limit)
