"""``/acquisitions``: upload (multipart), list, read, and raw frames (NPY, PNG preview)."""

from __future__ import annotations

import io
from typing import Annotated

import cv2
import numpy as np
from fastapi import File, Form, Header, Path, Query, Request, UploadFile
from fastapi.responses import Response

from rasterserver.api.deps import (
    MAX_OFFSET,
    CallerDep,
    NoteDep,
    PageDep,
    ServicesDep,
    Uid,
    not_modified,
    protected_router,
    utc,
)
from rasterserver.api.fields import AcquisitionKind, Day, FrameRole, Instant
from rasterserver.api.schemas import AcquisitionOut, UploadOut
from rasterserver.api.views import (
    acquisition_body,
    json_response,
    refuse_date_filters_for,
    resolve_patient,
)
from rasterserver.errors import NotFoundError
from rasterserver.frame_fit import calibration_notice
from rasterserver.ingest_request import ingest_request
from rasterserver.times import TIME_RULE

router = protected_router("acquisitions")

# The metadata reads (list, one acquisition) are ``async def`` and query through
# ``svc.read``: on SQLite on the event loop (each is one indexed query of well under a
# millisecond, and as plain ``def`` the hand-over to a thread and back cost more than the
# query under 50 concurrent clients), on PostgreSQL in a thread. Everything that reads
# pixels, writes or may take long is plain ``def``, in threads.

FrameIndex = Annotated[int, Path(ge=0, le=MAX_OFFSET)]


@router.get("/acquisitions", name="list_acquisitions", response_model=list[AcquisitionOut])
async def list_acquisitions(
    svc: ServicesDep, caller: CallerDep, note: NoteDep, page: PageDep,
    patient: Annotated[str | None, Query(max_length=64,
                                         description="Identifier (researchers: pseudonym).")]
    = None,
    since: Annotated[Instant | None, Query(description=f"Acquired at or after: {TIME_RULE}.")]
    = None,
    until: Annotated[Instant | None, Query(description="Acquired before (as since).")] = None,
    kind: Annotated[AcquisitionKind | None, Query()] = None,
) -> Response:
    """Acquisitions, newest first, by patient, time range and kind."""
    refuse_date_filters_for(caller, since, until)
    rows = await svc.read(
        svc.archive.find,
        patient=resolve_patient(caller, patient, svc.pseudonyms) if patient else None,
        since=utc(since), until=utc(until), kind=kind, limit=page.limit, offset=page.offset)
    for a in rows:
        note.touch(a.patient_id)
    return json_response([acquisition_body(a, caller, svc.pseudonyms) for a in rows])


@router.post("/acquisitions", name="upload_acquisition", response_model=UploadOut,
             status_code=201, responses={
                 200: {"model": UploadOut,
                       "description": "Stored before under this Idempotency-Key (a retry): "
                                      "the acquisition that was stored then"},
                 409: {"description": "The Idempotency-Key was used for a different upload"},
                 413: {"description": "Upload too large"},
                 422: {"description": "A frame or field was refused; nothing was stored"}})
def upload_acquisition(
    svc: ServicesDep, caller: CallerDep, note: NoteDep,
    files: Annotated[list[UploadFile], File(description="Frames: PNG, TIFF, NPY or raw.")],
    roles: Annotated[list[FrameRole] | None, Form(description="Role per frame, or one for "
                                                   "all.")] = None,
    patient: Annotated[str | None, Form(max_length=64)] = None,
    kind: Annotated[AcquisitionKind, Form()] = "patient",
    station: Annotated[str | None, Form(max_length=100)] = None,
    calibration_version: Annotated[int | None, Form(ge=1, le=2**31)] = None,
    visit_date: Annotated[Day | None, Form(description="YYYY-MM-DD; default: the day of "
                                                  "acquired_at at its offset.")] = None,
    acquired_at: Annotated[Instant | None, Form(description=f"{TIME_RULE}; default: now.")]
    = None,
    operator: Annotated[str, Form(max_length=100)] = "",
    notes: Annotated[str, Form(max_length=10_000)] = "",
    shape: Annotated[str | None, Form(max_length=32, description="ROWSxCOLS of raw frames.")]
    = None,
    dtype: Annotated[str | None, Form(max_length=16)] = None,
    convert_color: Annotated[bool, Form()] = False,
    idempotency_key: Annotated[str | None, Header(
        min_length=1, max_length=100,
        description="The client's key for this upload. Sent again with the same upload (a "
                    "retry after a timeout or a lost connection), it answers 200 with what "
                    "the first attempt stored instead of storing it twice.")] = None,
) -> Response:
    """Store one acquisition of one or several frames, validated like ``rasterserver ingest``.

    Every frame is decoded and checked before anything is written: one refused frame and
    nothing is stored. With an ``Idempotency-Key`` a retried upload is stored once. A frame
    whose size differs from the camera of the calibration that applies is refused (422);
    when no calibration applies yet, ``warnings`` says so and why.
    """
    request = ingest_request(
        [(f.file.read(), f.filename or f"frame-{k}") for k, f in enumerate(files)],
        roles=roles, patient=patient, kind=kind, station=station,
        calibration_version=calibration_version, visit_date=visit_date,
        acquired_at=utc(acquired_at), operator=operator, notes=notes, shape=shape,
        dtype=dtype, convert_color=convert_color, idempotency_key=idempotency_key,
        source=caller.name)
    acq, replayed = request.store(svc.archive)
    note.touch(acq.patient_id, acq.uid)
    # read back as a reader would see it
    info = svc.archive.info(acq.uid)
    notice = calibration_notice(svc.archive, info)
    body = acquisition_body(info, caller, svc.pseudonyms)
    body["warnings"] = [notice] if notice else []
    response = json_response(body, status_code=200 if replayed else 201)
    if replayed:
        response.headers["Idempotent-Replayed"] = "true"
    return response


@router.get("/acquisitions/{uid}", name="get_acquisition", response_model=AcquisitionOut)
async def get_acquisition(uid: Uid, svc: ServicesDep, caller: CallerDep, note: NoteDep) -> Response:
    """One acquisition with its frames' metadata."""
    info = await svc.read(svc.archive.info, uid)
    note.touch(info.patient_id, info.uid)
    return json_response(acquisition_body(info, caller, svc.pseudonyms))


def _frame_sha(svc: ServicesDep, note: NoteDep, uid: str, index: int) -> str:
    info = svc.archive.info(uid)
    note.touch(info.patient_id, info.uid)
    for f in info.frames:
        if f.index == index:
            return f.sha256
    raise NotFoundError(f"acquisition {uid} has no frame {index}")


_IMMUTABLE = "private, max-age=31536000, immutable"


@router.get("/acquisitions/{uid}/frames/{index}", name="get_frame",
            response_class=Response,
            responses={200: {"content": {"application/x-npy": {}},
                             "description": "The raw frame as a NumPy .npy file"},
                       304: {"description": "Not modified"}})
def get_frame(uid: Uid, index: FrameIndex, request: Request, svc: ServicesDep,
              note: NoteDep) -> Response:
    """The raw frame, bit for bit as stored, as NPY; its SHA-256 is the ETag."""
    sha = _frame_sha(svc, note, uid, index)
    if (cached := not_modified(request, sha)) is not None:
        return cached
    buffer = io.BytesIO()
    np.save(buffer, svc.archive.read_frame(uid, index), allow_pickle=False)
    return Response(buffer.getvalue(), media_type="application/x-npy",
                    headers={"ETag": f'"{sha}"', "Cache-Control": _IMMUTABLE,
                             "Content-Disposition": f'attachment; filename="{uid}-{index}.npy"'})


@router.get("/acquisitions/{uid}/frames/{index}/preview.png", name="get_frame_preview",
            response_class=Response,
            responses={200: {"content": {"image/png": {}}, "description": "8-bit PNG"},
                       304: {"description": "Not modified"}})
def get_frame_preview(uid: Uid, index: FrameIndex, request: Request, svc: ServicesDep,
                      note: NoteDep) -> Response:
    """An 8-bit PNG preview of the frame (16-bit frames scaled to their maximum)."""
    etag = _frame_sha(svc, note, uid, index) + "-png"
    if (cached := not_modified(request, etag)) is not None:
        return cached
    frame = svc.archive.read_frame(uid, index)
    if frame.dtype != np.uint8:
        peak = float(frame.max()) or 1.0
        frame = np.clip(frame.astype(np.float64) * (255.0 / peak), 0, 255).astype(np.uint8)
    ok, png = cv2.imencode(".png", frame)
    if not ok:  # pragma: no cover - a stored frame is always a 2-D integer image
        raise RuntimeError("PNG encoding failed")
    return Response(png.tobytes(), media_type="image/png",
                    headers={"ETag": f'"{etag}"', "Cache-Control": _IMMUTABLE})
