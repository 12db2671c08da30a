"""The one shaping of an ingest request, for the command line and the HTTP route.

``rasterserver ingest`` and ``POST /acquisitions`` receive the same upload in their own
forms (files and options; multipart fields and a header); each turns it into one
:class:`IngestRequest` with :func:`ingest_request` and stores it with
:meth:`IngestRequest.store`: the same checks, defaults and messages for both. What stays
with each front end is its own parsing (dates from text, times without zone as UTC).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rasterserver.catalog.vocabulary import ACQUISITION_KINDS
from rasterserver.errors import InputError
from rasterserver.ingest import AcquisitionSpec, FrameSource, ingest_many, ingest_once

if TYPE_CHECKING:
    from rasterserver.archive import Archive
    from rasterserver.catalog.models import Acquisition

__all__ = ["IngestRequest", "frame_roles", "ingest_request", "parse_shape"]


@dataclass(frozen=True)
class IngestRequest:
    """One upload as the command line or the HTTP API received it, checked and shaped.

    Attributes
    ----------
    spec : AcquisitionSpec
        The acquisition, with its idempotency key and its ``source`` (who uploads).
    shape, dtype, convert_color
        How to decode the frames (see :func:`rasterserver.ingest.ingest`).
    """

    spec: AcquisitionSpec
    shape: tuple[int, int] | None = None
    dtype: str | None = None
    convert_color: bool = False

    def store(self, archive: Archive) -> tuple[Acquisition, bool]:
        """Store the upload: once under its idempotency key if it has one.

        Returns
        -------
        (Acquisition, bool)
            The acquisition, and whether an earlier upload with the same key had stored it.
        """
        spec = self.spec
        decoding: dict[str, Any] = {"shape": self.shape, "dtype": self.dtype,
                                    "convert_color": self.convert_color}
        if spec.idempotency_key is None:
            return ingest_many(archive, [spec], **decoding)[0], False
        metadata: dict[str, Any] = {
            "kind": spec.kind, "visit_date": spec.visit_date, "station": spec.station,
            "calibration_version": spec.calibration_version, "acquired_at": spec.acquired_at,
            "operator": spec.operator, "notes": spec.notes}
        return ingest_once(archive, spec.frames, source=spec.source, key=spec.idempotency_key,
                           patient=spec.patient, **decoding, **metadata)


def parse_shape(text: str | None, option: str = "shape") -> tuple[int, int] | None:
    """Parse ``ROWSxCOLUMNS`` (the size of raw frames); None or empty gives None.

    Raises
    ------
    InputError
        Not two integers around an ``x``; the message names ``option``.
    """
    if not text:
        return None
    try:
        rows, cols = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise InputError(f"{option} {text!r}: expected ROWSxCOLUMNS, e.g. 604x576") from None
    return rows, cols


def frame_roles(roles: Sequence[str] | None, count: int, option: str = "roles") -> list[str]:
    """The role of each of ``count`` frames: one per frame, or one for all (``raster``
    by default).

    Raises
    ------
    InputError
        As many roles as neither one nor ``count``; the message names ``option``.
    """
    names = list(roles or ["raster"])
    if len(names) == 1:
        names = names * count
    if len(names) != count:
        raise InputError(f"{count} files but {len(names)} {option}")
    return names


def ingest_request(
    frames: Sequence[tuple[Path | bytes, str]],
    *,
    roles: Sequence[str] | None = None,
    patient: str | None = None,
    kind: str = "patient",
    station: str | None = None,
    calibration_version: int | None = None,
    visit_date: dt.date | None = None,
    acquired_at: dt.datetime | None = None,
    operator: str = "",
    notes: str = "",
    shape: str | None = None,
    dtype: str | None = None,
    convert_color: bool = False,
    idempotency_key: str | None = None,
    source: str = "",
    spelling: dict[str, str] | None = None,
) -> IngestRequest:
    """Shape an upload into an :class:`IngestRequest`, refusing what is wrong on its face.

    Parameters
    ----------
    frames : sequence of (Path or bytes, str)
        Each frame's file or bytes and its name (for messages and to tell the format).
    roles : sequence of str, optional
        As for :func:`frame_roles`.
    shape : str, optional
        ``ROWSxCOLUMNS`` of raw frames (:func:`parse_shape`).
    idempotency_key, source : str
        The client's key for this upload and who sends it (the account; ``cli``).
    spelling : dict, optional
        How the front end spells the ``shape`` and ``roles`` fields in messages
        (``{"shape": "--shape", "roles": "--role values"}`` for the command line).
    patient, kind, station, calibration_version, visit_date, acquired_at, operator, notes,
    dtype, convert_color
        As for :func:`rasterserver.ingest.ingest`.

    Returns
    -------
    IngestRequest

    Raises
    ------
    InputError
        An unknown kind, roles that do not match the frames, a malformed shape.
    """
    spelled = {"shape": "shape", "roles": "roles", **(spelling or {})}
    if kind not in ACQUISITION_KINDS:
        raise InputError(f"kind must be one of {', '.join(ACQUISITION_KINDS)}")
    names = frame_roles(roles, len(frames), spelled["roles"])
    sources = tuple(FrameSource(data, role=role, name=name)
                    for (data, name), role in zip(frames, names, strict=True))
    spec = AcquisitionSpec(
        frames=sources, patient=patient, kind=kind, visit_date=visit_date, station=station,
        calibration_version=calibration_version, acquired_at=acquired_at, operator=operator,
        notes=notes, idempotency_key=idempotency_key, source=source)
    return IngestRequest(spec, shape=parse_shape(shape, spelled["shape"]), dtype=dtype,
                         convert_color=convert_color)
