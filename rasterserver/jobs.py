"""Process many acquisitions with one coordinator loop, on one engine: here or on Dask.

The coordinator (this process) plans each acquisition (catalogue only: the run row, the
chain keys, what is stored already), hands the plan to the *engine*, and commits what comes
back: provenance rows, for every acquisition that came back together in one transaction.
The engine runs :func:`rasterserver.worker.work`: it reads the raw frame itself (read-only,
verified), computes and writes the derived files durably under their chain-key names, so
frames and records never pass through the coordinator. There is one loop (:func:`run_tasks`)
whatever the engine; engines differ only in where the work runs (:mod:`rasterserver.engines`):

* :class:`InProcess`: here, at once (one acquisition, or a machine where a cluster does not
  pay: see BENCHMARKS.md, "Reprocessing throughput").
* :class:`OnDask`: on a Dask cluster (the archive on storage the workers share): a
  ``LocalCluster`` started around the job, or the scheduler at ``--scheduler`` /
  ``RASTERSERVER_DASK_SCHEDULER``. A worker that dies mid-task has its task rerun by the
  scheduler on another worker (Dask's own retry, up to
  ``distributed.scheduler.allowed-failures``); files and rows are keyed by chain key, so a
  task computed twice is stored once (the second writer adopts the file, the row is
  inserted once).

A row is committed only after its files are durable, so it never names a missing file; a
coordinator killed between the two leaves files without rows that the rerun adopts.

At most ``in_flight`` acquisitions are planned ahead of the results coming back, so a job
over thousands of acquisitions holds only a few plans in memory. One acquisition failing
(no calibration, a frame of the wrong size) is recorded and the job goes on.

:func:`process_many` runs a list of uids and returns their outcomes (no job row);
:mod:`rasterserver.processing_jobs` runs the same loop over a job's task rows.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import islice
from typing import TYPE_CHECKING, Any, Literal

from rasterserver.archive import Archive
from rasterserver.chain import DEFAULT_TARGET, Computation, Plan
from rasterserver.engines import (
    LOCAL_CLUSTER_MIN,
    Engine,
    InProcess,
    OnDask,
    dask_client,
    engine_name,
    open_engine,
    quiet_dask_logs,
)
from rasterserver.errors import RasterServerError
from rasterserver.pipeline import Pipeline, ProcessResult
from rasterserver.registry import Registry

if TYPE_CHECKING:
    from distributed import Client

__all__ = [
    "LOCAL_CLUSTER_MIN",
    "Engine",
    "InProcess",
    "JobOutcome",
    "OnDask",
    "Progress",
    "dask_client",
    "open_engine",
    "process_many",
    "quiet_dask_logs",
    "run_tasks",
]

log = logging.getLogger(__name__)

#: Called with (done, total) after each acquisition.
Progress = Callable[[int, int], None]

#: Computed acquisitions whose rows the coordinator commits in one transaction, at most...
COMMIT_BATCH = 64
#: ...and the longest a computed acquisition waits for its rows (seconds): progress stays live
COMMIT_EVERY_S = 0.5


@dataclass(frozen=True)
class JobOutcome:
    """What happened to one acquisition of a job.

    Attributes
    ----------
    uid : str
        The acquisition.
    status : {"done", "failed"}
        Whether its chain ran to the end.
    computed, reused : int
        Stages computed now and stages whose stored result was reused.
    reason : str
        The last stage's reason (why the result is empty, or a note).
    error : str
        Why it failed; empty when done.
    results : tuple of (int, bool)
        Stage result id and whether it was reused, per stage (not in :meth:`to_dict`).
    exit_code : int
        The CLI exit code of the failure: its error's (3 for an unknown acquisition, 2 for a
        frame that does not fit), 1 for an unexpected one; 0 when done (not in
        :meth:`to_dict`).
    """

    uid: str
    status: Literal["done", "failed"]
    computed: int = 0
    reused: int = 0
    reason: str = ""
    error: str = ""
    results: tuple[tuple[int, bool], ...] = ()
    exit_code: int = 0

    @classmethod
    def done(cls, result: ProcessResult) -> JobOutcome:
        """The outcome of a processed acquisition."""
        return cls(
            result.uid,
            "done",
            result.computed,
            result.reused,
            result.reason,
            results=tuple((s.result_id, s.reused) for s in result.steps),
        )

    def then(self, other: JobOutcome) -> JobOutcome:
        """This outcome followed by ``other`` of the same acquisition (another target).

        A stage both chains share counts once: computed if the first computed it.
        """
        results = dict(self.results)
        for result_id, reused in other.results:
            results[result_id] = results.get(result_id, True) and reused
        reasons = [r for r in (self.reason, other.reason) if r]
        return JobOutcome(
            self.uid,
            "failed" if "failed" in (self.status, other.status) else "done",
            sum(not reused for reused in results.values()),
            sum(reused for reused in results.values()),
            "; ".join(dict.fromkeys(reasons)),
            self.error or other.error,
            tuple(results.items()),
            self.exit_code or other.exit_code,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: uid, status, computed, reused, reason, error."""
        return {
            "uid": self.uid,
            "status": self.status,
            "computed": self.computed,
            "reused": self.reused,
            "reason": self.reason,
            "error": self.error,
        }

    @classmethod
    def failed(cls, uid: str, exc: BaseException) -> JobOutcome:
        """The outcome of an acquisition that could not be processed."""
        if isinstance(exc, RasterServerError):
            return cls(uid, "failed", error=str(exc), exit_code=exc.exit_code)
        # a bug in a plugin or here: keep the job going, but say clearly what it was
        log.error("processing %s failed unexpectedly", uid, exc_info=exc)
        return cls(uid, "failed", error=f"{type(exc).__name__}: {exc}", exit_code=1)


# --- the coordinator loop ----------------------------------------------------------------------


#: What :func:`run_tasks` asks ``stop`` for: None to go on, ``"paused"`` to finish what is in
#: flight and stop, ``"cancelled"`` to drop what is in flight and stop.
StopReason = Literal["paused", "cancelled"] | None


class JobStoppedError(RasterServerError):
    """The job was paused or cancelled while this acquisition was being computed."""

    exit_code = 4


@dataclass
class _Task:
    index: int
    uid: str
    targets: list[str]
    outcome: JobOutcome | None = None

    def add(self, step: JobOutcome) -> bool:
        """Merge ``step``; whether the task is over (failed, or no target left)."""
        self.outcome = step if self.outcome is None else self.outcome.then(step)
        # a failure ends the task: the next target would fail the same way (no frame, no
        # calibration)
        return step.status == "failed" or not self.targets


def run_tasks(
    pipeline: Pipeline,
    tasks: Iterable[tuple[int, str]],
    *,
    engine: Engine,
    finished: Callable[[int, JobOutcome], None],
    targets: Sequence[str] = (DEFAULT_TARGET,),
    options: Mapping[str, Any] | None = None,
    stop: Callable[[], StopReason] | None = None,
    wait_s: float = 0.5,
    flush: Callable[[], None] | None = None,
    started: Callable[[list[int]], None] | None = None,
) -> StopReason:
    """Process ``tasks`` (index, uid) through ``targets`` on ``engine``: the coordinator loop.

    For each acquisition and target: :meth:`Pipeline.plan` here (catalogue only: the engine
    reads the frame; the first target of a page of new tasks with :meth:`Pipeline.plan_many`,
    a few queries for the page), the computing and the derived files on the engine
    (:func:`rasterserver.worker.work`), the rows here, for every result that came back
    together in one transaction (:meth:`Pipeline.commit_many`); the next target is planned
    after the previous one is stored, so it reuses the stages they share. Rows are committed
    when :data:`COMMIT_BATCH` results are waiting or :data:`COMMIT_EVERY_S` after the first
    of them came back, whichever is first.
    ``finished(index, outcome)`` is called once per task, after its results are committed,
    in the order tasks finish; ``flush()`` after each batch of them.

    Parameters
    ----------
    pipeline : Pipeline
        The coordinator's pipeline.
    tasks : iterable of (int, str)
        Read lazily, as room frees up (at most ``engine.in_flight`` tasks are in flight).
    engine : Engine
        Where the computing runs.
    finished : callable
        Called with (index, outcome) when a task is over.
    targets : sequence of str, optional
        Last stage kinds, one chain each, in order.
    options : Mapping, optional
        ``chain``, ``params``, ``calibration`` for :meth:`Pipeline.plan`.
    stop : callable, optional
        Asked between tasks and every ``wait_s`` while waiting: ``"paused"`` stops starting
        tasks and finishes those in flight; ``"cancelled"`` drops those in flight too (their
        runs are marked failed, nothing of them stored) except those already computed, whose
        files exist: their rows are committed.
    wait_s : float, optional
        Longest wait for a result before asking ``stop`` again.
    flush : callable, optional
        Called after each batch of ``finished`` calls and before returning (a job stores its
        task states in one transaction there).
    started : callable, optional
        Called with the indexes of the tasks just started (planned and submitted), a few at
        a time (a job counts their attempts there).

    Returns
    -------
    StopReason
        None when every task ran; else why the loop stopped (tasks not started are left).
    """
    options = dict(options or {})
    ask = stop or (lambda: None)
    after = flush or (lambda: None)
    source = iter(tasks)
    in_flight: dict[cf.Future[Computation], tuple[_Task, Plan]] = {}
    # computed (files on disk), rows not yet committed: committed together, at the latest
    # COMMIT_EVERY_S after the first of them came back
    ready: list[tuple[_Task, Plan, Computation]] = []
    oldest = 0.0
    born: dict[cf.Future[Computation], float] = {}
    stopping: StopReason = None

    def close(task: _Task, step: JobOutcome) -> bool:
        over = task.add(step)
        if over:
            assert task.outcome is not None
            finished(task.index, task.outcome)
        return over

    def advance(task: _Task, first: Plan | BaseException | None = None) -> None:
        # plan the task's next target (``first``: planned already, with its page): stored
        # ones are committed here, the first that needs computing goes to the engine
        while task.targets:
            target = task.targets.pop(0)
            given, first = first, None
            if isinstance(given, BaseException):
                close(task, JobOutcome.failed(task.uid, given))
                return
            if given is not None:
                plan = given
            else:
                try:
                    plan = pipeline.plan(task.uid, until=target, load_input=False, **options)
                except Exception as exc:
                    close(task, JobOutcome.failed(task.uid, exc))
                    return
            if not plan.needs_computing:  # everything stored already
                if close(task, _commit(pipeline, [(task, plan, Computation({}, {}, ""))])[0]):
                    return
                continue
            future = engine.submit(plan)
            if future.done():  # computed at once (in-process): its wait for rows starts now
                born[future] = time.monotonic()
            in_flight[future] = (task, plan)
            return

    def commit_ready() -> None:
        batch = ready[:]
        ready.clear()
        for (task, _plan, _c), outcome in zip(batch, _commit(pipeline, batch), strict=True):
            if not close(task, outcome):
                advance(task)
        after()

    while True:
        if stopping is None:
            stopping = ask()
        begun: list[int] = []
        while stopping is None and len(in_flight) < engine.in_flight:
            # a page of new tasks, their first target planned in bulk (a few queries for
            # the page, not a few per acquisition: the coordinator's main cost)
            room = engine.in_flight - len(in_flight)
            page = [_Task(i, u, list(targets)) for i, u in islice(source, room)]
            if not page:
                break
            begun.extend(task.index for task in page)
            first: list[Plan | BaseException | None] = [None] * len(page)
            if targets:
                try:
                    first = list(pipeline.plan_many(
                        [task.uid for task in page], until=targets[0], load_input=False,
                        **options,
                    ))
                except Exception as exc:  # the catalogue went away: each task fails alone
                    first = [exc] * len(page)
            for task, plan in zip(page, first, strict=True):
                advance(task, plan)
            stopping = ask()
        engine.flush()  # before waiting: an engine may hold submissions back to batch them
        if begun and started is not None:
            started(begun)
        if stopping == "cancelled":
            # what is computed is on disk already: its rows are committed, so that no file
            # is left without one; the rest is dropped (a task running on a Dask worker
            # cannot be stopped: its files, if it gets that far, are adopted by a rerun)
            for future, (task, plan) in in_flight.items():
                if future.done() and not future.cancelled() and future.exception() is None:
                    ready.append((task, plan, future.result()))
                else:
                    future.cancel()
                    pipeline.fail(plan.run_id, JobStoppedError("the job was cancelled"))
            in_flight.clear()
            born.clear()
            for (task, _plan, _c), outcome in zip(ready, _commit(pipeline, ready), strict=True):
                close(task, outcome)  # a task with targets left stays pending
            ready.clear()
        if not in_flight:
            if ready:
                commit_ready()  # may plan next targets: go round again
                continue
            after()
            return stopping
        timeout = wait_s if not ready else max(0.0, oldest + COMMIT_EVERY_S - time.monotonic())
        done, _ = cf.wait(list(in_flight), timeout=timeout, return_when=cf.FIRST_COMPLETED)
        for future in done:
            task, plan = in_flight.pop(future)
            came = born.pop(future, time.monotonic())
            try:
                computation = future.result()
            except Exception as exc:
                pipeline.fail(plan.run_id, exc)
                close(task, JobOutcome.failed(task.uid, exc))
                continue
            oldest = min(oldest, came) if ready else came
            ready.append((task, plan, computation))
        if done and not ready:
            after()  # failures only
        if ready and (
            len(ready) >= COMMIT_BATCH or time.monotonic() - oldest >= COMMIT_EVERY_S
        ):
            commit_ready()


def _commit(
    pipeline: Pipeline, batch: Sequence[tuple[_Task, Plan, Computation]]
) -> list[JobOutcome]:
    if not batch:
        return []
    try:
        # a job reports counts and reasons: no final record read back from its file
        results = pipeline.commit_many(
            [(plan, computation) for _t, plan, computation in batch], final=False
        )
    except Exception as exc:  # pragma: no cover - commit_many reports per acquisition
        return [JobOutcome.failed(plan.uid, exc) for _t, plan, _c in batch]
    return [
        JobOutcome.done(result)
        if isinstance(result, ProcessResult)
        else JobOutcome.failed(plan.uid, result)
        for (_t, plan, _c), result in zip(batch, results, strict=True)
    ]


def process_many(
    archive: Archive,
    uids: Sequence[str],
    *,
    chain: Mapping[str, str] | None = None,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    calibration: tuple[str, int | None] | None = None,
    until: str | Sequence[str] = DEFAULT_TARGET,
    dask: bool = False,
    client: Client | None = None,
    scheduler: str | None = None,
    n_workers: int | None = None,
    max_in_flight: int | None = None,
    progress: Progress | None = None,
    registry: Registry | None = None,
) -> list[JobOutcome]:
    """Process ``uids`` through the chain; stored results are reused, failures recorded.

    No job row: for a job that survives its process, see :mod:`rasterserver.processing_jobs`
    (the same loop, :func:`run_tasks`).

    Parameters
    ----------
    archive : Archive
        The archive.
    uids : sequence of str
        Acquisitions, processed (and reported) in this order.
    chain, params, calibration
        As for :meth:`rasterserver.pipeline.Pipeline.process`.
    until : str or sequence of str, optional
        Last stage kind, or several (``("mesh", "analysis")``): one chain each, in order; the
        later ones reuse what the earlier ones stored (the surface both start from).
    dask : bool, optional
        Compute on Dask: ``scheduler``, else the archive settings' ``dask_scheduler``, else a
        ``LocalCluster`` started and stopped here.
    client : distributed.Client, optional
        Use this client (implies ``dask``).
    scheduler : str, optional
        Scheduler address (implies ``dask``).
    n_workers : int, optional
        Workers of a local cluster started here.
    max_in_flight : int, optional
        Acquisitions planned but not yet stored, at most, on Dask.
    progress : Progress, optional
        Called with (done, total) at the start and after each acquisition.
    registry : Registry, optional
        Where the coordinator finds plugins (workers use their own).

    Returns
    -------
    list of JobOutcome
        One per uid, in the order given.
    """
    pipeline = Pipeline(archive, registry=registry)
    targets = [until] if isinstance(until, str) else list(dict.fromkeys(until))
    total = len(uids)
    report = progress or (lambda _done, _total: None)
    outcomes: dict[int, JobOutcome] = {}

    def finished(index: int, outcome: JobOutcome) -> None:
        outcomes[index] = outcome
        report(len(outcomes), total)

    name = engine_name(
        total,
        dask=bool(dask or client is not None),
        scheduler=scheduler,
        default_scheduler=archive.settings.dask_scheduler,
    )
    report(0, total)
    with open_engine(
        name, pipeline, client=client, n_workers=n_workers, in_flight=max_in_flight
    ) as engine:
        run_tasks(
            pipeline,
            enumerate(uids),
            engine=engine,
            finished=finished,
            targets=targets,
            options={"chain": chain, "params": params, "calibration": calibration},
        )
    return [outcomes[i] for i in range(total)]
