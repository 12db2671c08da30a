"""``/jobs``: processing on demand; POST returns a job to poll."""

from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query

from rasterserver.api.deps import CallerDep, NoteDep, PageDep, ServicesDep, protected_router, utc
from rasterserver.api.errors import scrub_paths
from rasterserver.api.schemas import JobIn, JobOut, JobOutcomeOut
from rasterserver.catalog.auth_models import ApiJob
from rasterserver.errors import InputError

router = protected_router("jobs")


def _job(job: ApiJob, root: object = "") -> JobOut:
    # errors are messages of the service, which may name archive files: not where they are
    return JobOut(
        id=job.id, status=job.status, done=job.done, total=job.total,
        created_at=utc(job.created_at), finished_at=utc(job.finished_at),  # type: ignore[arg-type]
        error=scrub_paths(job.error, root),
        outcomes=[JobOutcomeOut(**(o | {"error": scrub_paths(o.get("error", ""), root)}))
                  for o in job.outcomes])


@router.post("/jobs", name="start_job", response_model=JobOut, status_code=202)
def start_job(body: JobIn, svc: ServicesDep, caller: CallerDep, note: NoteDep) -> JobOut:
    """Process acquisitions through the stage chain in the background (like ``process``).

    Every uid must exist; stored results of the same computation are reused.
    """
    if body.calibration_version is not None and body.calibration_station is None:
        raise InputError("calibration_version needs calibration_station")
    uids = list(dict.fromkeys(body.uids))
    for uid in uids:
        acq = svc.archive.acquisition(uid)
        note.touch(acq.patient_id, acq.uid if len(uids) == 1 else None)
    calibration = ((body.calibration_station, body.calibration_version)
                   if body.calibration_station else None)
    job = svc.jobs.submit(uids, owner=caller.name, chain=body.chain or None,
                          params=body.params or None, calibration=calibration,
                          until=body.until)
    note.detail = f"job {job.id}"
    return _job(job, svc.settings.archive)


@router.get("/jobs", name="list_jobs", response_model=list[JobOut])
def list_jobs(svc: ServicesDep, page: PageDep,
              status: Annotated[str | None, Query(max_length=16)] = None) -> list[JobOut]:
    """Processing jobs, newest first."""
    return [_job(j, svc.settings.archive) for j in svc.jobs.list(status=status, limit=page.limit,
                                             offset=page.offset)]


@router.get("/jobs/{job_id}", name="get_job", response_model=JobOut)
def get_job(job_id: Annotated[str, Path(max_length=32)], svc: ServicesDep) -> JobOut:
    """A job's status, progress (acquisitions done of total) and outcomes."""
    return _job(svc.jobs.get(job_id), svc.settings.archive)
