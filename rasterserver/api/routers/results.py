"""Stored results of an acquisition, its pipeline runs, and exports (PLY/OBJ/STL/CSV)."""

from __future__ import annotations

import tempfile
from pathlib import Path as FilePath
from typing import Annotated

from fastapi import Path, Query, Request
from fastapi.responses import Response

from rasterserver.api.deps import (
    CallerDep,
    NoteDep,
    PageDep,
    ServicesDep,
    Uid,
    not_modified,
    protected_router,
    utc,
)
from rasterserver.api.schemas import ResultOut, RunOut
from rasterserver.api.views import Clock, patient_clock, pseudonymised, result_out, run_out
from rasterserver.errors import NotFoundError
from rasterserver.export import ExportFormat, ExportFrame, ExportWhat, select_export

router = protected_router("results")

Plugin = Annotated[str | None, Query(max_length=100, description="Only this plugin's.")]


_MEDIA = {"ply": "application/octet-stream", "obj": "text/plain", "stl": "model/stl",
          "csv": "text/csv"}


def _touch(svc: ServicesDep, note: NoteDep, uid: str, caller: CallerDep | None = None) -> Clock:
    """Audit the read of ``uid``'s data; return how ``caller`` sees the times of its records
    (shifted for researchers, see :func:`~rasterserver.api.views.patient_clock`)."""
    info = svc.archive.info(uid)
    note.touch(info.patient_id, info.uid)
    if caller is None:
        return utc
    return patient_clock(caller, info.patient, svc.pseudonyms)


@router.get("/acquisitions/{uid}/results", name="list_results", response_model=list[ResultOut])
def list_results(
    uid: Uid, svc: ServicesDep, caller: CallerDep, note: NoteDep, page: PageDep,
    stage: Annotated[str | None, Query(max_length=32)] = None, plugin: Plugin = None,
) -> list[ResultOut]:
    """Every stored stage result of the acquisition with its provenance, oldest first."""
    clock = _touch(svc, note, uid, caller)
    rows = [r for r in svc.pipeline.results(uid)
            if (stage is None or r.stage == stage) and (plugin is None or r.plugin == plugin)]
    return [result_out(r, clock) for r in rows[page.offset: page.offset + page.limit]]


@router.get("/acquisitions/{uid}/results/{stage}", name="get_result", response_model=ResultOut,
            responses={304: {"description": "Not modified"}})
def get_result(uid: Uid, stage: Annotated[str, Path(max_length=32)], request: Request,
               svc: ServicesDep, caller: CallerDep, note: NoteDep,
               plugin: Plugin = None) -> ResultOut | Response:
    """The newest stored result of one stage; stored results never change (ETag)."""
    clock = _touch(svc, note, uid, caller)
    rows = [r for r in svc.pipeline.results(uid)
            if r.stage == stage and (plugin is None or r.plugin == plugin)]
    if not rows:
        raise NotFoundError(f"acquisition {uid} has no stored {stage} result")
    row = max(rows, key=lambda r: (utc(r.created_at), r.id))
    # the two views differ (shifted times), so must their tags
    etag = row.output_checksum + ("-pseudonymised" if pseudonymised(caller) else "")
    if (cached := not_modified(request, etag)) is not None:
        return cached
    out = result_out(row, clock)
    return Response(out.model_dump_json(), media_type="application/json",
                    headers={"ETag": f'"{etag}"'})


@router.get("/acquisitions/{uid}/runs", name="list_runs", response_model=list[RunOut])
def list_runs(uid: Uid, svc: ServicesDep, caller: CallerDep, note: NoteDep, page: PageDep,
              status: Annotated[str | None, Query(max_length=16)] = None) -> list[RunOut]:
    """Pipeline runs of the acquisition, oldest first (researchers: times shifted by the
    patient's offset, like every time of a patient's data)."""
    clock = _touch(svc, note, uid, caller)
    rows = [r for r in svc.pipeline.runs(uid) if status is None or r.status == status]
    root = svc.settings.archive
    return [run_out(r, clock, root) for r in rows[page.offset: page.offset + page.limit]]


@router.get("/acquisitions/{uid}/export", name="export_result", response_class=Response,
            responses={200: {"content": {m: {} for m in sorted(set(_MEDIA.values()))},
                             "description": "The exported file"},
                       304: {"description": "Not modified"},
                       404: {"description": "No such acquisition, or it has no stored result "
                                            "of that kind (of that plugin): process it first"},
                       422: {"description": "The format cannot hold what is asked: csv holds "
                                            "points (what=points or smoothed, not mesh), obj "
                                            "and stl hold meshes (what=mesh); or the stored "
                                            "result holds nothing to export; or, with "
                                            "frame=patient, the analysis found no "
                                            "body-fixed frame (the reason is given)"}})
def export_result(
    uid: Uid, request: Request, svc: ServicesDep, note: NoteDep,
    fmt: Annotated[ExportFormat, Query(alias="format")] = ExportFormat.ply,
    what: Annotated[ExportWhat | None, Query(description="mesh (default), points or smoothed; "
                                             "points for csv")] = None,
    plugin: Plugin = None,
    frame: Annotated[ExportFrame, Query(
        description="station: the calibration's world frame (X right, Y down, Z anterior); "
        "patient: the body-fixed frame of the back-shape analysis (origin DM, X right, Y up, "
        "Z posterior); named in the X-Coordinate-Frame header")] = ExportFrame.station,
) -> Response:
    """The newest stored mesh or point cloud, as ``rasterserver export`` writes it.

    ``format`` and ``what`` must agree: ``ply`` takes any, ``obj`` and ``stl`` only ``mesh``,
    ``csv`` only ``points`` or ``smoothed`` (its default is ``points``); other combinations
    are refused with 422.
    """
    _touch(svc, note, uid)
    chosen = select_export(svc.pipeline, uid, fmt=fmt, what=what, plugin=plugin, frame=frame)
    etag = f"{chosen.row.output_checksum}-{chosen.what.value}-{frame.value}.{fmt.value}"
    if (cached := not_modified(request, etag)) is not None:
        return cached
    with tempfile.TemporaryDirectory(prefix="rasterserver-export-") as tmp:
        path = chosen.write(FilePath(tmp) / f"{uid}.{fmt.value}")
        data = path.read_bytes()
    return Response(data, media_type=_MEDIA[fmt.value], headers={
        "ETag": f'"{etag}"',
        "X-Coordinate-Frame": f"{frame.value}; units=mm",
        "Content-Disposition":
            f'attachment; filename="{uid}-{chosen.what.value}.{fmt.value}"'})
