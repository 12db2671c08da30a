"""``/jobs``: processing on demand; POST returns a job to poll; a job can be paused,
resumed (in a thread of this server) and cancelled, as with ``rasterserver jobs``."""

from __future__ import annotations

import logging
import threading
import time
from typing import Annotated

from fastapi import Path, Query

from rasterserver.api.deps import CallerDep, NoteDep, PageDep, ServicesDep, protected_router, utc
from rasterserver.api.errors import scrub_paths
from rasterserver.api.schemas import JobIn, JobOut, JobOutcomeOut
from rasterserver.errors import ConflictError, InputError, RasterServerError
from rasterserver.processing_jobs import (
    JobStatus,
    cancel_job,
    find_job,
    job_outcomes,
    job_status,
    pause_job,
    run_job,
)
from rasterserver.services.jobs import server_dask

router = protected_router("jobs")
log = logging.getLogger(__name__)
JobId = Annotated[str, Path(max_length=32)]


def _job(status: JobStatus, svc: object, root: object = "", *, outcomes: bool = True) -> JobOut:
    # errors are messages of the service, which may name archive files: not where they are
    job = status.job
    error = job.error
    state = status.state
    if status.interrupted:
        # reported as failed (clients poll while queued or running); the CLI finishes it
        state = "failed"
        error = (f"interrupted: the server process running this job stopped; "
                 f"`rasterserver jobs resume {job.id}` finishes it")
    finished = job_outcomes(svc.archive, job.id) if outcomes else []  # type: ignore[attr-defined]
    return JobOut(
        id=job.id, status=state, done=job.done, failed=job.failed, left=status.left,
        total=job.total, rate_per_s=status.rate, eta_s=status.eta_s,
        created_at=utc(job.created_at),
        started_at=utc(job.started_at), progress_at=utc(job.progress_at),
        finished_at=utc(job.finished_at),
        error=scrub_paths(error, root),
        outcomes=[JobOutcomeOut(**(o.to_dict() | {"error": scrub_paths(o.error, root)}))
                  for o in finished])


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
    note.detail = f"job {job.job.id}"
    return _job(job, svc, svc.settings.archive)


@router.get("/jobs", name="list_jobs", response_model=list[JobOut])
def list_jobs(svc: ServicesDep, page: PageDep,
              status: Annotated[str | None, Query(max_length=16)] = None) -> list[JobOut]:
    """Processing jobs, newest first (their outcomes: ``GET /jobs/{id}``)."""
    jobs = svc.jobs.list(status=status, limit=page.limit, offset=page.offset)
    return [_job(j, svc, svc.settings.archive, outcomes=False) for j in jobs]


@router.get("/jobs/{job_id}", name="get_job", response_model=JobOut)
def get_job(job_id: Annotated[str, Path(max_length=32)], svc: ServicesDep) -> JobOut:
    """A job's status, progress (acquisitions done, failed and left of total, rate, ETA) and
    the outcomes of its finished acquisitions. The same job as `rasterserver jobs show ID`."""
    return _job(svc.jobs.get(job_id), svc, svc.settings.archive)


@router.post("/jobs/{job_id}/pause", name="pause_job", response_model=JobOut)
def pause(job_id: JobId, svc: ServicesDep, note: NoteDep) -> JobOut:
    """Pause a queued or running job: its coordinator stores the acquisitions in flight and
    stops; ``POST /jobs/{id}/resume`` continues it. 409 when it is not queued or running."""
    job = pause_job(svc.archive, job_id)
    note.detail = f"job {job.id} paused"
    return _job(job_status(svc.archive, job), svc, svc.settings.archive, outcomes=False)


@router.post("/jobs/{job_id}/cancel", name="cancel_job", response_model=JobOut)
def cancel(job_id: JobId, svc: ServicesDep, note: NoteDep) -> JobOut:
    """Cancel a job for good: pending acquisitions are not processed; stored results stay.
    409 when it is finished or cancelled already."""
    job = cancel_job(svc.archive, job_id)
    note.detail = f"job {job.id} cancelled"
    return _job(job_status(svc.archive, job), svc, svc.settings.archive, outcomes=False)


@router.post("/jobs/{job_id}/resume", name="resume_job", response_model=JobOut,
             status_code=202)
def resume(job_id: JobId, svc: ServicesDep, note: NoteDep) -> JobOut:
    """Resume a paused job, or one whose process stopped (a server restarted mid-job), in a
    thread of this server: only its pending acquisitions are processed. 409 when it is
    queued, running in a live process, finished or cancelled."""
    status = job_status(svc.archive, find_job(svc.archive, job_id))
    if status.state not in ("paused", "interrupted"):
        raise ConflictError(f"job {status.job.id} is {status.state}: only a paused or "
                            "interrupted job can be resumed")
    job_id = status.job.id
    archive = svc.archive

    def run() -> None:
        try:
            run_job(archive, job_id, dask=server_dask(archive))
        except RasterServerError as exc:  # recorded in the row by run_job
            log.warning("processing job %s stopped: %s", job_id, exc)
        except Exception:
            log.exception("processing job %s failed", job_id)

    # a thread of its own: the job survives this request, and if the server stops it is
    # reported interrupted and can be resumed again
    thread = threading.Thread(target=run, name=f"rasterserver-job-{job_id[:8]}", daemon=True)
    thread.start()
    note.detail = f"job {job_id} resumed"
    # answer once the thread has taken the job (running), so that a client polling while
    # it is queued or running does not stop at the state it had before
    deadline = time.monotonic() + 5.0
    while status.state in ("paused", "interrupted") and time.monotonic() < deadline:
        time.sleep(0.05)
        status = job_status(svc.archive, find_job(svc.archive, job_id))
        if not thread.is_alive():
            break
    return _job(status, svc, svc.settings.archive, outcomes=False)
