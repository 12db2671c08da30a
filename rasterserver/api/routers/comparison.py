"""The comparison of two acquisitions of a patient and the patient's parameter trends.

Both read what ``process`` (or a job) stored, through the service behind ``rasterserver
compare`` (:mod:`rasterserver.visit_comparison`), in memory: a GET never processes anything.
An acquisition without a stored analysis answers 404, visits that cannot be compared (other
patients, no landmark frame, ICP not converging) 422 with the reason. Researchers get the
patient's pseudonym and every date shifted by the patient's offset: whole days, the same for
every visit, so the intervals between visits are the true ones.
"""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from fastapi import Query
from fastapi.responses import Response
from pydantic import BaseModel, Field

from rasterserver.api.deps import CallerDep, NoteDep, ServicesDep, Uid, protected_router
from rasterserver.api.routers.analysis import AcquisitionRef
from rasterserver.api.routers.patients import PatientRef
from rasterserver.api.views import acquisition_body, json_response, pseudonymised, resolve_patient
from rasterserver.services.auth import Principal
from rasterserver.visit_comparison import COMPARISON_FORMAT, TwoVisits

router = protected_router("comparison")


class ComparisonOut(BaseModel):
    format: str = Field(COMPARISON_FORMAT)
    frame: str
    a: str = Field(description="The earlier acquisition (uid).")
    b: str = Field(description="The later acquisition, registered onto A.")
    acquisitions: list[AcquisitionRef] = Field(description="A and B (researchers: shifted).")
    registration: dict[str, Any] = Field(
        description="transform (4×4, B's world frame to A's), landmark_start, fitness, "
        "rmse_mm, points, landmark_start_from (how the start was made: both visits' body "
        "frames, or without one visit's VP), icp_rotation_deg, icp_translation_mm."
    )
    distance: dict[str, Any] = Field(
        description="Statistics of B − A along A's normals (mm, + posterior): rms, largest, "
        "areas beyond ±2 mm and ±5 mm."
    )
    asymmetry: dict[str, dict[str, Any]] = Field(
        description="Per uid: `statistics` of its asymmetry map, or `refused` (the reason)."
    )
    asymmetry_change: dict[str, Any] | None = Field(
        description="Statistics of the change of the asymmetry map, null when one is refused."
    )


class TrendVisitOut(BaseModel):
    label: str = Field(description="Acquisition uid.")
    date: str | None = Field(description="When acquired (researchers: shifted).")
    value: float | None
    change: float | None = Field(description="From the previous visit with a value.")
    flagged: bool = Field(description="|change| > sdc.")
    vp_carried_from: str | None = Field(
        None,
        description="The acquisition whose VP the value was measured with, carried through "
        "their registration because this acquisition's analysis did not find its own; null: "
        "its own.",
    )


class TrendOut(BaseModel):
    parameter: str
    unit: str
    sd: float | None = Field(description="Repeatability SD, or null (never flagged).")
    sdc: float | None = Field(description="Smallest detectable change, 1.96·√2·SD.")
    visits: list[TrendVisitOut]
    first_to_last: dict[str, Any]
    flagged: bool


class TrendsOut(BaseModel):
    format: str = Field("rasterserver.trends/1")
    patient: str = Field(description="Identifier (researchers: pseudonym).")
    sdc: str
    sd_source: str
    parameters: list[TrendOut]


_NOT_FOUND = "Unknown acquisition or patient, or no stored analysis (process it first)"
_RESPONSES: dict[int | str, dict[str, Any]] = {
    404: {"description": _NOT_FOUND},
    422: {
        "description": "Not comparable: the same acquisition twice, different patients, a "
        "visit without landmark frame, ICP not converging (the reason is in `detail`)"
    },
}


def _compare(
    uid_a: str, uid_b: str, svc: ServicesDep, caller: Principal, note: NoteDep
) -> tuple[TwoVisits, list[dict[str, Any]]]:
    from rasterserver.visit_comparison import compare_two

    for uid in (uid_a, uid_b):
        info = svc.archive.info(uid)
        note.touch(info.patient_id, info.uid)
    result = compare_two(svc.pipeline, uid_a, uid_b)
    refs = []
    for uid in (result.a.uid, result.b.uid):
        body = acquisition_body(svc.archive.info(uid), caller, svc.pseudonyms)
        refs.append({"uid": uid, "patient": body["patient"], "acquired_at": body["acquired_at"]})
    return result, refs


@router.get(
    "/acquisitions/{uid_a}/comparison/{uid_b}",
    name="get_comparison",
    response_model=ComparisonOut,
    responses=_RESPONSES,
)
def get_comparison(
    uid_a: Uid, uid_b: Uid, svc: ServicesDep, caller: CallerDep, note: NoteDep
) -> Response:
    """The comparison of two acquisitions of one patient: the later visit (B) registered onto
    the earlier (A), the distance map's and the asymmetry maps' statistics.

    Computed from the stored analyses, surfaces and meshes, which are not processed here. The
    comparison and each visit's asymmetry map are stage results: the first read computes and
    stores them (derived data, keyed by the results compared; `provenance` says whether they
    were reused), later reads reuse them. Either order of the uids gives the same answer.
    """
    result, refs = _compare(uid_a, uid_b, svc, caller, note)
    return json_response(result.document | {"acquisitions": refs})


@router.get(
    "/acquisitions/{uid_a}/comparison/{uid_b}/distance.png",
    name="get_comparison_distance",
    response_class=Response,
    responses={
        200: {"content": {"image/png": {}}, "description": "The distance map B − A"},
        **_RESPONSES,
    },
)
def get_comparison_distance(
    uid_a: Uid, uid_b: Uid, svc: ServicesDep, caller: CallerDep, note: NoteDep
) -> Response:
    """The distance map B − A seen from behind, colour-mapped (red: B posterior of A), with
    a scale bar in mm and A's landmarks; titled with the visits' dates (researchers:
    shifted)."""
    result, refs = _compare(uid_a, uid_b, svc, caller, note)
    data = result.distance_png(refs[0]["acquired_at"], refs[1]["acquired_at"])
    return Response(
        data,
        media_type="image/png",
        headers={
            "Content-Disposition": f'inline; filename="distance_{result.a.uid}-{result.b.uid}.png"'
        },
    )


@router.get(
    "/patients/{patient:path}/trends",
    name="get_patient_trends",
    response_model=TrendsOut,
    responses={
        200: {"content": {"text/csv": {}}, "description": "The trends (JSON or CSV)"},
        404: {"description": _NOT_FOUND},
    },
)
def get_patient_trends(
    patient: PatientRef,
    svc: ServicesDep,
    caller: CallerDep,
    note: NoteDep,
    format: Annotated[Literal["json", "csv"], Query(description="json (default) or csv.")] = "json",
) -> Response:
    """Every analysis parameter over the patient's acquisitions, oldest first, with the change
    from the previous visit, flagged only beyond the smallest detectable change.

    An acquisition whose analysis found nothing is a gap (null values). Researchers name the
    patient by pseudonym and get shifted dates (the intervals between visits are the true
    ones).
    """
    from rasterserver.trends import TrendVisit, trends, trends_csv, trends_document
    from rasterserver.visit_comparison import trend_visits

    identifier = resolve_patient(caller, patient, svc.pseudonyms)
    row = svc.archive.patient(identifier)
    note.touch(row.id)
    shown = row.identifier
    visits = trend_visits(svc.pipeline, row.identifier)
    if pseudonymised(caller):
        shown = svc.pseudonyms.pseudonym(row.identifier)

        def when(at: dt.datetime) -> dt.datetime:
            shifted = svc.pseudonyms.shift_time(row.identifier, at)
            assert shifted is not None
            return shifted
    else:

        def when(at: dt.datetime) -> dt.datetime:
            return at

    table = trends([TrendVisit(uid, when(at), parameters) for uid, at, parameters in visits])
    if format == "csv":
        return Response(
            trends_csv(table),
            media_type="text/csv; charset=utf-8",
            headers={"Content-Disposition": 'inline; filename="trends.csv"'},
        )
    return json_response({"patient": shown} | trends_document(table))
