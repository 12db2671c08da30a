"""Processing jobs of the HTTP API: a small in-process executor over :func:`process_many`.

A POST starts a job and returns at once; the job runs :func:`rasterserver.jobs.process_many`
(the CLI's ``process``) in a worker thread of the server process that accepted it. Its state
lives in the catalogue (``api_job``), so any server worker can report status and progress,
and a restart keeps the history. A job whose process has gone (a restart mid-job) is
reported as failed: its finished acquisitions' results are stored, the rest can be
resubmitted and will reuse them.
"""

from __future__ import annotations

import datetime as dt
import uuid
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from sqlalchemy import select, update

from rasterserver.archive import Archive
from rasterserver.catalog.auth_models import ApiJob
from rasterserver.errors import NotFoundError
from rasterserver.jobs import process_many
from rasterserver.pipeline import DEFAULT_TARGETS
from rasterserver.runner import current_runner, runner_gone


class JobRunner:
    """Runs processing jobs in ``workers`` background threads of this process.

    Parameters
    ----------
    archive : Archive
        The archive (and its catalogue, where jobs are kept).
    workers : int
        Jobs run at the same time here (each processes its acquisitions one by one).
    """

    def __init__(self, archive: Archive, *, workers: int = 1) -> None:
        self.archive = archive
        self._pool = ThreadPoolExecutor(max_workers=max(1, workers),
                                        thread_name_prefix="rasterserver-job")

    def submit(
        self,
        uids: Sequence[str],
        *,
        owner: str,
        chain: Mapping[str, str] | None = None,
        params: Mapping[str, Mapping[str, Any]] | None = None,
        calibration: tuple[str, int | None] | None = None,
        until: str | Sequence[str] = DEFAULT_TARGETS,
    ) -> ApiJob:
        """Queue a job over ``uids`` and return its row (status ``queued``)."""
        job = ApiJob(id=uuid.uuid4().hex, owner=owner, uids=list(uids), status="queued",
                     done=0, total=len(uids), runner=current_runner(), error="", outcomes=[])
        with self.archive.session() as s:
            s.add(job)
        job_id = job.id

        def set_state(**values: Any) -> None:
            with self.archive.session() as s:
                s.execute(update(ApiJob).where(ApiJob.id == job_id).values(**values))

        def run() -> None:
            set_state(status="running")
            try:
                outcomes = process_many(
                    self.archive, list(uids), chain=chain, params=params,
                    calibration=calibration, until=until,
                    progress=lambda done, _total: set_state(done=done),
                )
                failed = any(o.status == "failed" for o in outcomes)
                set_state(status="failed" if failed else "done",
                          outcomes=[o.to_dict() for o in outcomes],
                          finished_at=dt.datetime.now(dt.UTC))
            except Exception as exc:  # a bad chain or parameters: the whole job failed
                set_state(status="failed", error=str(exc)[:2000] or type(exc).__name__,
                          finished_at=dt.datetime.now(dt.UTC))

        self._pool.submit(run)
        return job

    def get(self, job_id: str) -> ApiJob:
        """Return job ``job_id`` or raise :class:`NotFoundError`."""
        with self.archive.session() as s:
            job = s.get(ApiJob, job_id)
        if job is None:
            raise NotFoundError(f"unknown job {job_id}")
        return self._checked(job)

    def list(self, *, status: str | None = None, limit: int = 100,
             offset: int = 0) -> list[ApiJob]:
        """Jobs, newest first, optionally with one status."""
        query = select(ApiJob).order_by(ApiJob.created_at.desc(), ApiJob.id)
        if status is not None:
            query = query.where(ApiJob.status == status)
        with self.archive.session() as s:
            return [self._checked(j) for j in s.scalars(query.limit(limit).offset(offset))]

    @staticmethod
    def _checked(job: ApiJob) -> ApiJob:
        if job.status in ("queued", "running") and runner_gone(job.runner):
            job.status = "failed"
            job.error = "the server process running this job stopped; submit it again"
        return job

    def close(self) -> None:
        """Stop accepting jobs; running ones finish."""
        self._pool.shutdown(wait=False, cancel_futures=True)
