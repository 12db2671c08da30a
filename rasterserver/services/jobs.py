"""Processing jobs of the HTTP API: catalogue jobs (:mod:`rasterserver.processing_jobs`) run
by threads of the server process.

A POST creates the job, with its tasks, in the catalogue and returns at once; a worker thread
of the server that accepted it runs it (:func:`rasterserver.processing_jobs.run_job`, the loop
``rasterserver process`` runs). Any server worker reports its status and progress from the
row, and the CLI sees it too (``rasterserver jobs show ID``), and can pause or cancel it. A job
whose server process has gone (a restart mid-job) is reported as failed, "interrupted", and
``rasterserver jobs resume ID`` finishes it: its finished acquisitions are not redone.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any

from rasterserver.errors import RasterServerError
from rasterserver.pipeline import DEFAULT_TARGETS
from rasterserver.processing_jobs import (
    JobStatus,
    Selection,
    create_job,
    find_job,
    job_status,
    list_jobs,
    run_job,
)

if TYPE_CHECKING:
    from rasterserver.archive import Archive

log = logging.getLogger(__name__)


def server_dask(archive: Archive) -> bool | None:
    """How a job started by the HTTP server computes: on ``RASTERSERVER_DASK_SCHEDULER`` if
    one is set, else in the server's own process (``dask`` of
    :func:`rasterserver.processing_jobs.run_job`).

    A server's threads do not start a local cluster of worker processes beside the web
    server, whatever the job's size: a clinic that wants more sets up a scheduler.
    """
    return None if archive.settings.dask_scheduler else False


class JobRunner:
    """Runs processing jobs in ``workers`` background threads of this process.

    Parameters
    ----------
    archive : Archive
        The archive (and its catalogue, where jobs are kept).
    workers : int
        Jobs run at the same time here.
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
    ) -> JobStatus:
        """Store a job over ``uids`` (state ``queued``), start it in a thread, return it.

        A bad chain, parameters or calibration is refused here, before anything is stored.
        """
        targets = [until] if isinstance(until, str) else list(until)
        job, _count = create_job(
            self.archive, Selection(uids=tuple(uids)), chain=chain, params=params,
            calibration=calibration, targets=targets, owner=owner, origin="http",
        )
        job_id = job.id

        def run() -> None:
            try:
                run_job(self.archive, job_id, dask=server_dask(self.archive))
            except RasterServerError as exc:  # recorded in the row by run_job
                log.warning("processing job %s stopped: %s", job_id, exc)
            except Exception:
                log.exception("processing job %s failed", job_id)

        self._pool.submit(run)
        return job_status(self.archive, job)

    def get(self, job_id: str) -> JobStatus:
        """Job ``job_id`` or :class:`~rasterserver.errors.NotFoundError`."""
        return job_status(self.archive, find_job(self.archive, job_id), failures=0)

    def list(self, *, status: str | None = None, limit: int = 100,
             offset: int = 0) -> list[JobStatus]:
        """Jobs, newest first, optionally with one stored state."""
        return [job_status(self.archive, j)
                for j in list_jobs(self.archive, state=status, limit=limit, offset=offset)]

    def close(self) -> None:
        """Stop accepting jobs; running ones finish."""
        self._pool.shutdown(wait=False, cancel_futures=True)
