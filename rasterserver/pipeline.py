"""Process archived acquisitions: the chain (:mod:`rasterserver.chain`) with stored results.

:class:`Pipeline`, for an archived acquisition: read its raster frame (never modifying it),
resolve its calibration, run the chain, store each stage's output in a derived HDF5 file
(:mod:`rasterserver.store.derived`) and record a :class:`~rasterserver.catalog.models.
StageResult` row with full provenance (:mod:`rasterserver.result_rows`), inside a
:class:`~rasterserver.catalog.models.PipelineRun` row.

Every result is stored under its chain key (:func:`rasterserver.chain.chain_keys`): the
longest stored prefix of a chain is loaded and only the rest is computed.

Work is split so that a Dask worker can do the computing: :meth:`Pipeline.plan` (catalogue
and files, in the driver), :func:`~rasterserver.chain.compute` (pure, anywhere) and
:meth:`Pipeline.commit` (files and rows, in the driver).

Interrupted runs
----------------
A run is committed ``running`` before anything is computed, naming its runner (the driver
process). If that process is killed, nothing finishes the row, so whenever runs are listed
(:meth:`Pipeline.runs`), an acquisition is planned or the unprocessed ones are selected, a
``running`` run of this host whose process is gone is stored as ``failed`` with an error
beginning :data:`INTERRUPTED` (:func:`rasterserver.runner.reap_runs`). Runs of other hosts
cannot be checked from here and are left; :meth:`Pipeline.reap` marks them when told their
host has stopped. Nothing else needs repairing: results are committed only with their files,
and a file written before the kill is adopted by the next run of the same computation.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import socket
from collections.abc import Mapping, Sequence
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError as SQLIntegrityError

from rasterserver import __version__
from rasterserver.archive import Archive
from rasterserver.catalog.models import (
    Acquisition,
    Frame,
    PipelineRun,
)
from rasterserver.chain import (
    DEFAULT_TARGET,
    DEFAULT_TARGETS,
    CachedResult,
    ChainStep,
    Computation,
    Plan,
    chain_keys,
    compute,
    parse_stage_options,
    resolve_chain,
    run_chain,
)
from rasterserver.errors import IntegrityError, NotFoundError, RasterServerError
from rasterserver.frame_fit import check_frame_fits
from rasterserver.pipeline_queries import PipelineQueries
from rasterserver.plan_inputs import (
    ChainInputs,
    InputsCache,
    acquisitions_by_uid,
    raster_frame,
    stored_results,
    stored_results_many,
)
from rasterserver.records import Record
from rasterserver.registry import Registry, get_registry
from rasterserver.result_rows import ProcessResult, StepOutcome, commit_rows, commit_rows_many
from rasterserver.runner import INTERRUPTED, ReapReport, current_runner, reap_runs
from rasterserver.stage import StageContext
from rasterserver.store.derived import DerivedStore
from rasterserver.worker import input_record, store_computed, work

__all__ = [
    "DEFAULT_TARGET",
    "DEFAULT_TARGETS",
    "INTERRUPTED",
    "ChainStep",
    "Computation",
    "Pipeline",
    "Plan",
    "ProcessResult",
    "ReapReport",
    "StepOutcome",
    "chain_keys",
    "check_frame_fits",
    "compute",
    "parse_stage_options",
    "resolve_chain",
    "run_chain",
]

log = logging.getLogger(__name__)


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def _message(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, RasterServerError) else f"{type(exc).__name__}: {exc}"


def _new_run(
    acquisition: Acquisition, steps: Sequence[ChainStep], calibration_id: int | None
) -> PipelineRun:
    """A ``running`` run row of ``steps`` over ``acquisition``, naming this process."""
    return PipelineRun(
        acquisition_id=acquisition.id,
        chain=[step.describe() for step in steps],
        status="running",
        started_at=_now(),
        host=socket.gethostname(),
        runner=current_runner(),
        package_version=__version__,
        calibration_id=calibration_id,
    )


class Pipeline(PipelineQueries):
    """Processing of archived acquisitions with stored results, provenance and reuse.

    Parameters
    ----------
    archive : Archive
        The archive (catalogue and raw store).
    registry : Registry, optional
        Where plugins are found.
    """

    def __init__(self, archive: Archive, *, registry: Registry | None = None) -> None:
        self.archive = archive
        self.registry = registry or get_registry()
        self.derived = DerivedStore(archive.settings.archive, resolve=self.registry.record_type)
        # per request and per calibration row: a job plans thousands of acquisitions with one
        # chain and a few calibrations (calibration rows never change once stored)
        self._chains: dict[str, list[ChainStep]] = {}
        self._inputs = InputsCache(archive)

    # --- the three phases ------------------------------------------------------------------

    def plan(
        self,
        uid: str,
        *,
        chain: Mapping[str, str] | None = None,
        params: Mapping[str, Mapping[str, Any]] | None = None,
        calibration: tuple[str, int | None] | None = None,
        until: str = DEFAULT_TARGET,
        frame_index: int | None = None,
        load_input: bool = True,
    ) -> Plan:
        """Resolve the chain, the frame and the calibration; find stored results; open a run.

        A :class:`PipelineRun` row is committed with status ``running``, naming this process
        as its runner; if anything after that fails, the run is marked ``failed`` with the
        message and the error re-raised. Earlier runs of the acquisition left ``running`` by a
        killed process of this host are marked interrupted in the same transaction.

        Parameters
        ----------
        uid : str
            Acquisition uid.
        chain, params, until
            As for :func:`run_chain`.
        calibration : (str, int or None), optional
            Station name and calibration version (None: newest) to use instead of the one
            attached at ingest. It must belong to the acquisition's station.
        frame_index : int, optional
            Frame to process; the first ``raster`` frame by default.
        load_input : bool, optional
            Read the input record here (the raw frame, or the stored result the computing
            starts from) into ``plan.input_record``. False leaves it to whoever computes
            (:func:`rasterserver.worker.work`, on a worker): the coordinator then touches
            no file.

        Returns
        -------
        Plan

        Raises
        ------
        NotFoundError
            Unknown acquisition, station or calibration; no calibration attached or given.
        InputError
            Bad chain or parameters, no raster frame, a calibration of another station, an
            invalid calibration document, or a frame of another size than the camera's.
        IntegrityError
            A stored result to be reused is missing or altered.
        """
        steps = self._steps(chain, params, until)
        acquisition = self.archive.acquisition(uid)
        frame, inputs, calibration_id, keys, problem = self._keyed(
            acquisition, frame_index, calibration, steps
        )
        # one transaction: the run opened and the stored results looked up
        with self.archive.session() as s:
            # a run its killed process left "running" must not look like work in progress
            # beside the new one
            reap_runs(s, acquisition_id=acquisition.id, local_only=True)
            run = _new_run(acquisition, steps, calibration_id)
            s.add(run)
            stored = stored_results(s, acquisition.id, keys) if keys else {}
        try:
            if problem is not None:
                raise problem
            assert frame is not None and inputs is not None  # no problem: both were found
            return self._plan(acquisition, run.id, steps, keys, stored, frame, inputs, load_input)
        except BaseException as exc:
            self.fail(run.id, exc)
            raise

    def plan_many(
        self,
        uids: Sequence[str],
        *,
        chain: Mapping[str, str] | None = None,
        params: Mapping[str, Mapping[str, Any]] | None = None,
        calibration: tuple[str, int | None] | None = None,
        until: str = DEFAULT_TARGET,
        frame_index: int | None = None,
        load_input: bool = False,
    ) -> list[Plan | BaseException]:
        """:meth:`plan` for a page of acquisitions, with the catalogue work done in bulk.

        What :meth:`plan` does per acquisition in three sessions (the acquisition and its
        frames, the runs its killed processes left, a new run and the stored results), here
        in two for the whole page: one query for the acquisitions with their frames, one
        transaction that opens every run (marking failed at once those whose inputs are
        wrong) and looks up the stored results of every chain key. This is what keeps a
        job's coordinator at a few milliseconds per acquisition.

        Parameters
        ----------
        uids : sequence of str
            Acquisition uids (a page: a few dozen).
        chain, params, calibration, until, frame_index, load_input
            As for :meth:`plan`.

        Returns
        -------
        list of Plan or BaseException
            Per uid, in order: its plan, or the error :meth:`plan` would have raised (its
            run, if one was opened, is marked failed with it).
        """
        steps = self._steps(chain, params, until)
        with self.archive.session() as s:
            found = acquisitions_by_uid(s, uids)
        outcomes: list[Plan | BaseException] = []
        opened: list[tuple[int, Acquisition, PipelineRun, Any, Any, list[str]]] = []
        with self.archive.session() as s:
            ids = [a.id for a in found.values()]
            if ids:
                # earlier runs left "running" by a killed process (rare: one query to see)
                stale = s.scalars(
                    select(PipelineRun.acquisition_id)
                    .where(PipelineRun.status == "running", PipelineRun.acquisition_id.in_(ids))
                    .distinct()
                ).all()
                for acquisition_id in stale:
                    reap_runs(s, acquisition_id=acquisition_id, local_only=True)
            runs: list[PipelineRun] = []
            for position, uid in enumerate(uids):
                acquisition = found.get(uid)
                if acquisition is None:
                    outcomes.append(NotFoundError(f"unknown acquisition {uid}"))
                    continue
                outcomes.append(NotFoundError(uid))  # replaced below
                frame, inputs, calibration_id, keys, problem = self._keyed(
                    acquisition, frame_index, calibration, steps
                )
                run = _new_run(acquisition, steps, calibration_id)
                if problem is not None:
                    run.status, run.finished_at = "failed", _now()
                    run.error = _message(problem)[:10_000]
                    outcomes[position] = problem
                else:
                    opened.append((position, acquisition, run, frame, inputs, keys))
                runs.append(run)
            s.add_all(runs)
            s.flush()
            stored = stored_results_many(s, {entry[1].id: entry[5] for entry in opened})
        for position, acquisition, run, frame, inputs, keys in opened:
            try:
                outcomes[position] = self._plan(
                    acquisition,
                    run.id,
                    steps,
                    keys,
                    stored.get(acquisition.id, {}),
                    frame,
                    inputs,
                    load_input,
                )
            except Exception as exc:
                self.fail(run.id, exc)
                outcomes[position] = exc
        return outcomes

    def _keyed(
        self,
        acquisition: Acquisition,
        frame_index: int | None,
        calibration: tuple[str, int | None] | None,
        steps: list[ChainStep],
    ) -> tuple[Frame | None, ChainInputs | None, int | None, list[str], BaseException | None]:
        """The frame, calibration inputs and chain keys of one acquisition, or the problem.

        A problem is returned, not raised: the caller records it in the acquisition's run.
        """
        frame: Frame | None = None
        inputs: ChainInputs | None = None
        calibration_id: int | None = None
        try:
            frame = raster_frame(acquisition, frame_index)
            inputs = self._inputs.get(acquisition, calibration)
            calibration_id = inputs.row_id
            check_frame_fits((frame.height, frame.width), inputs.station)
            keys = chain_keys(
                frame.sha256,
                frame.index,
                steps,
                calibration_sha=inputs.sha256,
                raster_sha=inputs.raster_sha256,
            )
        except Exception as exc:
            return frame, inputs, calibration_id, [], exc
        return frame, inputs, calibration_id, keys, None

    def _steps(
        self,
        chain: Mapping[str, str] | None,
        params: Mapping[str, Mapping[str, Any]] | None,
        until: str,
    ) -> list[ChainStep]:
        # resolved once per request: a job plans thousands of acquisitions with one chain
        key = json.dumps([chain or {}, params or {}, until], sort_keys=True, default=repr)
        steps = self._chains.get(key)
        if steps is None:
            steps = resolve_chain(chain, params=params, until=until, registry=self.registry)
            self._chains[key] = steps
        return list(steps)

    def _plan(
        self,
        acquisition: Acquisition,
        run_id: int,
        steps: list[ChainStep],
        keys: list[str],
        rows: dict[str, CachedResult],
        frame: Frame,
        inputs: ChainInputs,
        load_input: bool,
    ) -> Plan:
        uid = acquisition.uid
        cached: list[CachedResult | None] = []
        for key in keys:
            row = rows.get(key)
            if row is None or (cached and cached[-1] is None):
                cached.append(None)
                continue
            cached.append(row)
        first = next((i for i, c in enumerate(cached) if c is None), len(steps))
        plan = Plan(
            uid=uid,
            acquisition_id=acquisition.id,
            run_id=run_id,
            frame_index=frame.index,
            calibration_id=inputs.row_id,
            steps=steps,
            keys=keys,
            cached=cached,
            first=first,
            input_record=None,
            input_checksum="",
            context=StageContext(calibration=inputs.station, raster=inputs.raster),
            frame_role=frame.role,
        )
        if load_input and plan.needs_computing:
            plan.input_record = input_record(plan, self.archive.settings.archive, self.derived)
            plan.input_checksum = plan.input_record.content_hash()
        return plan

    def compute(self, plan: Plan) -> Computation:
        """Compute and store (files only) the steps of ``plan`` without stored results, here.

        See :func:`rasterserver.worker.work`; every computed record is kept in the result.
        """
        try:
            return work(plan, self.archive.settings.archive, registry=self.registry, keep="all")
        except BaseException as exc:
            self.fail(plan.run_id, exc)
            raise

    def commit(self, plan: Plan, computation: Computation) -> ProcessResult:
        """Store the computed records' provenance; finish the run.

        Files are written (durably) before their rows; a crash in between leaves files that
        the next run adopts, because their names follow from their chain keys.
        """
        try:
            (outcome,) = self.commit_many([(plan, computation)])
        except BaseException as exc:  # the catalogue went away (commit_many reports the rest)
            self.fail(plan.run_id, exc)
            raise
        if isinstance(outcome, BaseException):
            raise outcome
        return outcome

    def commit_many(
        self, done: Sequence[tuple[Plan, Computation]], *, final: bool = True
    ) -> list[ProcessResult | BaseException]:
        """:meth:`commit` for several acquisitions, in one transaction when all goes well.

        Each acquisition's rows go in a savepoint of their own: one failing (its run is then
        marked failed) does not undo the others. Records the computation did not write
        (plain :func:`~rasterserver.chain.compute`) are written here first.

        Parameters
        ----------
        done : Sequence of (Plan, Computation)
            The acquisitions computed (or found stored) and what was computed.
        final : bool, optional
            Set each result's ``final`` record: from the computation, or read from its file
            when the computation does not hold it. A job, which reports counts and reasons
            only, passes False and reads no file.

        Returns
        -------
        list of ProcessResult or BaseException
            Per acquisition, in order: its result, or the error that failed it.
        """
        outcomes: list[ProcessResult | BaseException | None] = [None] * len(done)
        ready: list[int] = []
        for position, (plan, computation) in enumerate(done):
            try:
                self._store_files(plan, computation)
            except Exception as exc:
                outcomes[position] = exc
                continue
            ready.append(position)
        try:
            with self.archive.session() as s:
                one_by_one = ready
                try:
                    # all acquisitions' rows in a few statements; a row another process
                    # stored meanwhile (rare), or any other failure, undoes them all, and
                    # they go one by one below, each failing alone
                    with s.begin_nested():
                        fast = commit_rows_many(s, [done[position] for position in ready])
                    for position, result in zip(ready, fast, strict=True):
                        outcomes[position] = result
                    one_by_one = []
                except Exception:
                    log.debug("bulk insert of %d acquisitions' rows undone", len(ready))
                for position in one_by_one:
                    plan, computation = done[position]
                    try:
                        try:
                            with s.begin_nested():
                                outcomes[position] = commit_rows(
                                    s, plan, computation, adopt=False
                                )
                        except SQLIntegrityError:
                            # a row stored meanwhile by another process (rare): again, row
                            # by row, adopting it
                            with s.begin_nested():
                                outcomes[position] = commit_rows(s, plan, computation)
                    except Exception as exc:
                        outcomes[position] = exc
        except Exception as exc:  # the transaction itself failed: nothing of it is stored
            for position in ready:
                outcomes[position] = exc
        results: list[ProcessResult | BaseException] = []
        for (plan, computation), outcome in zip(done, outcomes, strict=True):
            assert outcome is not None
            if isinstance(outcome, ProcessResult):
                self._finish(outcome, computation, final=final)
            else:
                self.fail(plan.run_id, outcome)
            results.append(outcome)
        return results

    def _store_files(self, plan: Plan, computation: Computation) -> None:
        store_computed(self.derived, plan, computation, plan.input_checksum)

    def _finish(self, result: ProcessResult, computation: Computation, *, final: bool) -> None:
        record = computation.records.get(result.steps[-1].kind) if result.steps else None
        if record is None and result.steps and final:
            last = result.steps[-1]
            record = self.derived.read(last.store_path, expected_checksum=last.output_checksum)
        result.final = record
        log.info(
            "processed acquisition %s: %d stage(s) computed, %d reused",
            result.uid,
            result.computed,
            result.reused,
        )

    def process(
        self,
        uid: str,
        *,
        chain: Mapping[str, str] | None = None,
        params: Mapping[str, Mapping[str, Any]] | None = None,
        calibration: tuple[str, int | None] | None = None,
        until: str = DEFAULT_TARGET,
        frame_index: int | None = None,
    ) -> ProcessResult:
        """Process one acquisition in this process: plan, compute, commit.

        See :meth:`plan` for the parameters and errors.

        Returns
        -------
        ProcessResult
        """
        plan = self.plan(
            uid,
            chain=chain,
            params=params,
            calibration=calibration,
            until=until,
            frame_index=frame_index,
        )
        return self.commit(plan, self.compute(plan))

    # --- helpers ---------------------------------------------------------------------------

    def _load(self, cached: CachedResult) -> Record:
        try:
            return self.derived.read(cached.store_path, expected_checksum=cached.output_checksum)
        except NotFoundError:
            raise IntegrityError(
                f"stored result {cached.store_path} is missing; run `rasterserver verify`"
            ) from None

    def fail(self, run_id: int, exc: BaseException) -> None:
        """Mark run ``run_id`` failed with the message of ``exc`` (if it is still running)."""
        message = _message(exc)
        try:
            with self.archive.session() as s:
                run = s.get(PipelineRun, run_id)
                if run is not None and run.status == "running":
                    run.status = "failed"
                    run.finished_at = _now()
                    run.error = message[:10_000]
        except Exception:  # the original error matters more than failing to record it
            log.exception("could not mark pipeline run %s as failed", run_id)
