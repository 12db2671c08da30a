"""Processing jobs of the HTTP API: a small in-process executor over :func:`process_many`.

A POST starts a job and returns at once; the job runs :func:`rasterserver.jobs.process_many`
(the CLI's ``process``) in a worker thread, and its status and progress can be polled. Jobs
live in this process's memory: with several uvicorn workers, poll the worker that answered
(or run one worker), and a restart forgets the jobs, though never their stored results.
"""

from __future__ import annotations

import datetime as dt
import threading
import uuid
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal

from rasterserver.archive import Archive
from rasterserver.errors import NotFoundError
from rasterserver.jobs import JobOutcome, process_many
from rasterserver.pipeline import DEFAULT_TARGET

JobStatus = Literal["queued", "running", "done", "failed"]


@dataclass
class Job:
    """One processing job: its acquisitions, status, progress and outcomes."""

    id: str
    owner: str
    uids: list[str]
    status: JobStatus = "queued"
    done: int = 0
    total: int = 0
    created_at: dt.datetime = field(default_factory=lambda: dt.datetime.now(dt.UTC))
    finished_at: dt.datetime | None = None
    outcomes: list[JobOutcome] = field(default_factory=list)
    error: str = ""


class JobRunner:
    """Runs processing jobs in ``workers`` background threads.

    Parameters
    ----------
    archive : Archive
        The archive.
    workers : int
        Jobs run at the same time (each processes its acquisitions one by one).
    keep : int
        Finished jobs remembered, newest first.
    """

    def __init__(self, archive: Archive, *, workers: int = 1, keep: int = 1000) -> None:
        self.archive = archive
        self._pool = ThreadPoolExecutor(max_workers=max(1, workers),
                                        thread_name_prefix="rasterserver-job")
        self._jobs: dict[str, Job] = {}
        self._lock = threading.Lock()
        self._keep = keep

    def submit(
        self,
        uids: Sequence[str],
        *,
        owner: str,
        chain: Mapping[str, str] | None = None,
        params: Mapping[str, Mapping[str, Any]] | None = None,
        calibration: tuple[str, int | None] | None = None,
        until: str = DEFAULT_TARGET,
    ) -> Job:
        """Queue a job over ``uids`` and return it (status ``queued``)."""
        job = Job(id=uuid.uuid4().hex, owner=owner, uids=list(uids), total=len(uids))
        with self._lock:
            self._jobs[job.id] = job
            self._forget_old()

        def progress(done: int, total: int) -> None:
            job.done, job.total = done, total

        def run() -> None:
            job.status = "running"
            try:
                job.outcomes = process_many(
                    self.archive, job.uids, chain=chain, params=params,
                    calibration=calibration, until=until, progress=progress,
                )
                job.status = ("failed" if any(o.status == "failed" for o in job.outcomes)
                              else "done")
            except Exception as exc:  # a bad chain or parameters: the whole job failed
                job.error = str(exc) or type(exc).__name__
                job.status = "failed"
            finally:
                job.finished_at = dt.datetime.now(dt.UTC)

        self._pool.submit(run)
        return job

    def get(self, job_id: str) -> Job:
        """Return job ``job_id`` or raise :class:`NotFoundError`."""
        with self._lock:
            job = self._jobs.get(job_id)
        if job is None:
            raise NotFoundError(f"unknown job {job_id}")
        return job

    def list(self, *, status: str | None = None, limit: int = 100, offset: int = 0) -> list[Job]:
        """Jobs, newest first, optionally with one status."""
        with self._lock:
            jobs = sorted(self._jobs.values(), key=lambda j: j.created_at, reverse=True)
        if status is not None:
            jobs = [j for j in jobs if j.status == status]
        return jobs[offset: offset + limit]

    def _forget_old(self) -> None:
        finished = [j for j in self._jobs.values() if j.finished_at is not None]
        finished.sort(key=lambda j: j.created_at)
        for job in finished[: max(0, len(finished) - self._keep)]:
            del self._jobs[job.id]

    def close(self) -> None:
        """Stop accepting jobs; running ones finish."""
        self._pool.shutdown(wait=False, cancel_futures=True)
