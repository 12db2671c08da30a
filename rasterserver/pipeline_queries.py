"""What a :class:`~rasterserver.pipeline.Pipeline` has stored: results, runs, what is left.

The read side of the pipeline service (and reaping and verification, which read before they
mark), kept apart from planning and committing so each module holds one concept.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from sqlalchemy import exists, select

from rasterserver.catalog.models import Acquisition, Frame, PipelineRun, StageResult
from rasterserver.errors import NotFoundError
from rasterserver.integrity import VerifyReport, verify_derived
from rasterserver.records import Record
from rasterserver.runner import ReapReport, reap_runs

if TYPE_CHECKING:
    from rasterserver.archive import Archive
    from rasterserver.store.derived import DerivedStore


class PipelineQueries:
    """Queries of stored results and runs, shared by :class:`~rasterserver.pipeline.Pipeline`."""

    archive: Archive
    derived: DerivedStore

    def result(
        self, uid: str, stage: str, *, plugin: str | None = None
    ) -> tuple[StageResult, Record]:
        """The newest stored result of ``stage`` for acquisition ``uid``, with its record.

        Raises
        ------
        NotFoundError
            Unknown acquisition, or nothing of that stage stored (the message says how to
            process it).
        """
        acquisition = self.archive.acquisition(uid)
        query = select(StageResult).where(
            StageResult.acquisition_id == acquisition.id, StageResult.stage == stage
        )
        if plugin is not None:
            query = query.where(StageResult.plugin == plugin)
        with self.archive.session() as s:
            row = s.scalar(query.order_by(StageResult.created_at.desc(), StageResult.id.desc()))
        if row is None:
            which = f" by {plugin}" if plugin else ""
            raise NotFoundError(
                f"acquisition {uid} has no stored {stage} result{which}: "
                f"run `rasterserver process {uid}` first"
            )
        return row, self.derived.read(row.store_path, expected_checksum=row.output_checksum)

    def results(self, uid: str) -> list[StageResult]:
        """Every stored result of ``uid``, oldest first."""
        acquisition = self.archive.acquisition(uid)
        with self.archive.session() as s:
            return list(
                s.scalars(
                    select(StageResult)
                    .where(StageResult.acquisition_id == acquisition.id)
                    .order_by(StageResult.id)
                )
            )

    def runs(self, uid: str) -> list[PipelineRun]:
        """Every pipeline run of ``uid``, oldest first.

        A ``running`` run of this host whose process is gone is marked interrupted first
        (``failed``, error beginning :data:`~rasterserver.runner.INTERRUPTED`), so it is
        never listed as running.
        """
        acquisition = self.archive.acquisition(uid)
        query = (
            select(PipelineRun)
            .where(PipelineRun.acquisition_id == acquisition.id)
            .order_by(PipelineRun.id)
        )
        with self.archive.session() as s:
            rows = list(s.scalars(query))
            # one query when nothing is running, the usual case
            if any(row.status == "running" for row in rows):
                report = reap_runs(s, acquisition_id=acquisition.id, local_only=True)
                if report.marked:
                    rows = list(s.scalars(query.execution_options(populate_existing=True)))
            return rows

    def reap(self, *, hosts: Sequence[str] = (), dry_run: bool = False) -> ReapReport:
        """Mark every run left ``running`` by a process that is gone as interrupted.

        Runs of this host are checked (see :func:`rasterserver.runner.runner_gone`); those of
        a live process are left alone. Runs of another host cannot be checked from here:
        they are marked only if that host is named in ``hosts``, by someone who knows that
        nothing processes there any more. Marked runs get status ``failed`` and an error
        beginning :data:`~rasterserver.runner.INTERRUPTED` that says which process ran them.

        Parameters
        ----------
        hosts : sequence of str, optional
            Hosts whose ``running`` runs are to be taken as stopped. Naming this host marks
            its runs recorded without a runner (before revision 0008), never a live one.
        dry_run : bool, optional
            Count, change nothing.

        Returns
        -------
        ReapReport
        """
        report = ReapReport()
        with self.archive.session() as s:
            reap_runs(s, report, declared=frozenset(hosts), dry_run=dry_run)
        return report

    def unprocessed(self, *, patient: str | None = None, limit: int = 100_000) -> list[str]:
        """Uids of acquisitions with a raster frame and no successful run, oldest first.

        Runs that killed processes of this host left ``running`` are marked interrupted
        first, so that a reprocessing job does not find them still "in progress".
        """
        done = exists().where(
            PipelineRun.acquisition_id == Acquisition.id, PipelineRun.status == "done"
        )
        has_raster = exists().where(Frame.acquisition_id == Acquisition.id, Frame.role == "raster")
        query = select(Acquisition.uid).where(~done, has_raster)
        with self.archive.session() as s:
            reap_runs(s, local_only=True)
            if patient is not None:
                query = query.where(Acquisition.patient_id == self.archive.patient(patient, s).id)
            query = query.order_by(Acquisition.acquired_at, Acquisition.id).limit(limit)
            return list(s.scalars(query))

    def verify(self, *, progress: Callable[[int, int], None] | None = None) -> VerifyReport:
        """Check stored results against their rows: every row's file exists and matches.

        See :func:`rasterserver.integrity.verify_derived` (problems ``missing``, ``corrupt``,
        ``orphaned``: the next run of the same computation adopts it, ``temporary`` and
        ``stray``).

        Returns
        -------
        rasterserver.integrity.VerifyReport
            ``frames_checked`` counts the results checked.
        """
        return verify_derived(self.archive.catalog, self.derived, progress=progress)
