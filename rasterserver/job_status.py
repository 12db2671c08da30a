"""What a processing job has done: its status (counts, rate, time left, whether its
coordinator is gone) and the outcomes of its tasks, for ``jobs show`` and the HTTP API."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import select

from rasterserver.archive import Archive
from rasterserver.catalog.job_models import ProcessingJob, ProcessingTask
from rasterserver.jobs import JobOutcome
from rasterserver.runner import describe_runner, runner_gone

__all__ = ["JobStatus", "job_outcomes", "job_status", "to_utc"]


def to_utc(value: dt.datetime) -> dt.datetime:
    """``value`` in UTC (the catalogue gives aware UTC times; a naive one is taken as UTC)."""
    return value.replace(tzinfo=dt.UTC) if value.tzinfo is None else value.astimezone(dt.UTC)


@dataclass
class JobStatus:
    """A job as a user sees it: its row, whether its coordinator is gone, rate and ETA.

    Attributes
    ----------
    job : ProcessingJob
        The row.
    interrupted : bool
        Stored ``queued``/``running`` but its coordinator's process is gone: resumable.
    left : int
        Tasks not finished.
    rate : float or None
        Tasks finished per second by the current (or last) coordinator.
    eta_s : float or None
        Seconds to the end at that rate, while running.
    """

    job: ProcessingJob
    interrupted: bool = False
    left: int = 0
    rate: float | None = None
    eta_s: float | None = None
    failures: list[dict[str, Any]] = field(default_factory=list)

    @property
    def state(self) -> str:
        """The stored state, ``interrupted`` when its coordinator is gone."""
        return "interrupted" if self.interrupted else self.job.state

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (``jobs show --json``)."""
        job = self.job

        def when(value: dt.datetime | None) -> str | None:
            return None if value is None else to_utc(value).isoformat()

        return {
            "id": job.id,
            "state": self.state,
            "origin": job.origin,
            "owner": job.owner,
            "selection": job.selection,
            "targets": job.targets,
            "chain": job.chain,
            "engine": job.engine,
            "total": job.total,
            "done": job.done,
            "failed": job.failed,
            "left": self.left,
            "rate_per_s": self.rate,
            "eta_s": self.eta_s,
            "runner": describe_runner(job.runner) if job.runner else "",
            "error": job.error,
            "created_at": when(job.created_at),
            "started_at": when(job.started_at),
            "progress_at": when(job.progress_at),
            "finished_at": when(job.finished_at),
            "failures": self.failures,
        }


def _gone(job: ProcessingJob) -> bool:
    return job.state in ("queued", "running") and bool(job.runner) and runner_gone(job.runner)


def job_status(archive: Archive, job: ProcessingJob, *, failures: int = 0) -> JobStatus:
    """What :class:`JobStatus` says of ``job``, with up to ``failures`` failed tasks."""
    left = job.total - job.done - job.failed
    status = JobStatus(job, interrupted=_gone(job), left=left)
    if job.resumed_at is not None and job.progress_at is not None:
        spent = (to_utc(job.progress_at) - to_utc(job.resumed_at)).total_seconds()
        finished = job.done + job.failed - job.resumed_count
        if spent > 0 and finished > 0:
            status.rate = finished / spent
            if job.state == "running" and not status.interrupted:
                status.eta_s = left / status.rate
    if failures:
        with archive.session() as s:
            rows = s.scalars(
                select(ProcessingTask)
                .where(ProcessingTask.job_id == job.id, ProcessingTask.state == "failed")
                .order_by(ProcessingTask.position)
                .limit(failures)
            )
            status.failures = [
                {"uid": t.uid, "error": t.error, "exit_code": t.exit_code} for t in rows
            ]
    return status


def job_outcomes(archive: Archive, job_id: str, *, limit: int | None = None) -> list[JobOutcome]:
    """The outcomes of a job's finished tasks, in the selection's order."""
    query = (
        select(ProcessingTask)
        .where(ProcessingTask.job_id == job_id, ProcessingTask.state != "pending")
        .order_by(ProcessingTask.position)
    )
    if limit is not None:
        query = query.limit(limit)
    with archive.session() as s:
        return [
            JobOutcome(
                t.uid, "done" if t.state == "done" else "failed", t.computed, t.reused,
                t.reason, t.error, exit_code=t.exit_code,
            )
            for t in s.scalars(query)
        ]
