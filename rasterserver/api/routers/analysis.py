"""The back-shape analysis of an acquisition: landmarks and parameters (JSON), and the
one-page report (PNG, PDF).

Both read what ``process`` (or a job) stored; a GET never computes: an acquisition without
a stored analysis answers 404, one whose analysis found nothing 422 with the reason.
Researchers get the same data, pseudonymised: the patient's pseudonym, and every time shifted
by the patient's offset.
"""

from __future__ import annotations

import datetime as dt
import hashlib
from typing import Any

from fastapi import Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from rasterserver.analysis import DOCUMENT_FORMAT, Analysis, acquisition_analysis
from rasterserver.api.deps import (
    CallerDep,
    NoteDep,
    ServicesDep,
    Uid,
    not_modified,
    protected_router,
)
from rasterserver.api.views import acquisition_body, json_response, pseudonymised
from rasterserver.archive import AcquisitionInfo
from rasterserver.services.auth import Principal

router = protected_router("analysis")


class CoordinateFrameOut(BaseModel):
    name: str
    unit: str
    axes: str
    gravity: list[float] | None = Field(description="Direction of gravity in this frame.")
    calibration: str = Field(description="STATION:VERSION of the calibration used.")


class ParameterOut(BaseModel):
    value: float | None
    unit: str = Field(description="mm, deg (or 1).")
    spread: float | None = Field(description="Standard deviation over the frames, or null.")


class ReasonOut(BaseModel):
    what: str
    why: str


class BodyFrameOut(BaseModel):
    origin: list[float]
    axes: dict[str, list[float]]


class FrameAnalysisOut(BaseModel):
    name: str
    index: int | None
    analysed: bool
    reason: str
    provenance: dict[str, Any] | None = None


class AcquisitionRef(BaseModel):
    uid: str
    patient: str | None = Field(description="Identifier (researchers: pseudonym).")
    acquired_at: dt.datetime = Field(description="Researchers: shifted by the patient's offset.")


class AnalysisOut(BaseModel):
    format: str = Field(DOCUMENT_FORMAT)
    uid: str
    acquisition: AcquisitionRef
    frame: CoordinateFrameOut
    landmarks: dict[str, list[float] | None] = Field(
        description="VP, DL, DR, DM, SP: [x, y, z] mm in `frame`, null when not found."
    )
    landmark_confidence: dict[str, float]
    sagittal_points: dict[str, list[float] | None] = Field(
        description="ICT, KA, ITL, LA, ILS: inflection points and apices of the sagittal "
        "profile, [x, y, z] mm in `frame`, null when not found."
    )
    body_frame: BodyFrameOut | None
    parameters: dict[str, ParameterOut]
    reasons: list[ReasonOut] = Field(description="What could not be found, and why.")
    frames: list[FrameAnalysisOut]
    plugin: dict[str, str]


_RESPONSES: dict[int | str, dict[str, Any]] = {
    304: {"description": "Not modified"},
    404: {"description": "Unknown acquisition, or no stored analysis (process it first)"},
    422: {"description": "The analysis found nothing (the reason is in `detail`)"},
}


def _read(
    uid: str, svc: ServicesDep, caller: Principal, note: NoteDep, *, surfaces: bool
) -> tuple[Analysis, AcquisitionInfo, dict[str, Any], str]:
    """The checked analysis, the acquisition's entry and what ``caller`` may see of it, and
    the ETag (which differs between identified and pseudonymised views)."""
    info = svc.archive.info(uid)
    note.touch(info.patient_id, info.uid)
    analysis = acquisition_analysis(svc.pipeline, uid, surfaces=surfaces).check()
    body = acquisition_body(info, caller, svc.pseudonyms)
    acquisition = {"uid": info.uid, "patient": body["patient"], "acquired_at": body["acquired_at"]}
    checksums = "/".join(f.result.output_checksum for f in analysis.frames if f.result)
    view = "pseudonymised" if pseudonymised(caller) else "identified"
    etag = hashlib.sha256(f"{checksums}|{view}".encode()).hexdigest()[:32]
    return analysis, info, acquisition, etag


@router.get(
    "/acquisitions/{uid}/analysis",
    name="get_analysis",
    response_model=AnalysisOut,
    responses=_RESPONSES,
)
def get_analysis(
    uid: Uid, request: Request, svc: ServicesDep, caller: CallerDep, note: NoteDep
) -> Response:
    """The back-shape analysis: landmarks, parameters, what was not found, and provenance.

    Landmarks are ``[x, y, z]`` mm in the calibration's world frame (``frame``); parameters
    carry their unit and, over several raster frames, their spread. Stored results never
    change (ETag).
    """
    analysis, info, acquisition, etag = _read(uid, svc, caller, note, surfaces=False)
    if (cached := not_modified(request, etag)) is not None:
        return cached
    identifier = info.patient
    shift = None
    if pseudonymised(caller) and identifier:

        def shift(when: dt.datetime) -> dt.datetime:
            shifted = svc.pseudonyms.shift_time(identifier, when)
            assert shifted is not None
            return shifted

    document = analysis.document(shift_time=shift)
    document["acquisition"] = acquisition
    response = json_response(document)
    response.headers["ETag"] = f'"{etag}"'
    return response


def _report(
    uid: str, request: Request, svc: ServicesDep, caller: Principal, note: NoteDep, fmt: str
) -> Response:
    from rasterserver.analysis_report import render_report

    analysis, _info, acquisition, etag = _read(uid, svc, caller, note, surfaces=True)
    etag = f"{etag}-{fmt}"
    if (cached := not_modified(request, etag)) is not None:
        return cached
    when = acquisition["acquired_at"]
    header = [
        f"acquisition {uid}",
        f"patient {acquisition['patient']}" if acquisition["patient"] else "no patient",
        f"acquired {when:%Y-%m-%d %H:%M} UTC" + (" (shifted)" if pseudonymised(caller) else ""),
    ]
    data = render_report(analysis, header=header, fmt=fmt)
    media = "image/png" if fmt == "png" else "application/pdf"
    return Response(
        data,
        media_type=media,
        headers={
            "ETag": f'"{etag}"',
            "Content-Disposition": f'inline; filename="{uid}-analysis.{fmt}"',
        },
    )


@router.get(
    "/acquisitions/{uid}/analysis/report.png",
    name="get_analysis_report",
    response_class=Response,
    responses={
        200: {"content": {"image/png": {}}, "description": "The one-page report"},
        **_RESPONSES,
    },
)
def get_analysis_report(
    uid: Uid, request: Request, svc: ServicesDep, caller: CallerDep, note: NoteDep
) -> Response:
    """The one-page report as PNG: relief and curvature maps with landmarks, symmetry line and
    midline, frontal and sagittal midline, surface rotation, the parameter table."""
    return _report(uid, request, svc, caller, note, "png")


@router.get(
    "/acquisitions/{uid}/analysis/report.pdf",
    name="get_analysis_report_pdf",
    response_class=Response,
    responses={
        200: {"content": {"application/pdf": {}}, "description": "The one-page report"},
        **_RESPONSES,
    },
)
def get_analysis_report_pdf(
    uid: Uid, request: Request, svc: ServicesDep, caller: CallerDep, note: NoteDep
) -> Response:
    """The one-page report as PDF (the same page as the PNG)."""
    return _report(uid, request, svc, caller, note, "pdf")
