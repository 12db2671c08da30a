"""Process many acquisitions with one coordinator loop, on one engine: here or on Dask.

The coordinator (this process) plans each acquisition (catalogue lookups, reading the raw
frame or a stored intermediate result), hands the input record, the resolved chain and the
station data to the *engine*, and stores what comes back (derived files, provenance rows).
The computing is pure, so it can run anywhere; workers never touch the archive or the
catalogue. There is one loop (:func:`run_tasks`) whatever the engine; engines differ only in
where :func:`rasterserver.pipeline.compute` runs:

* :class:`InProcess`: here, at once (one acquisition, or a machine where a cluster does not
  pay: see BENCHMARKS.md, "Processing jobs").
* :class:`OnDask`: on a Dask cluster: a ``LocalCluster`` started around the job, or the
  scheduler at ``--scheduler`` / ``RASTERSERVER_DASK_SCHEDULER``. A worker that dies
  mid-task has its task rerun by the scheduler on another worker (Dask's own retry, up to
  ``distributed.scheduler.allowed-failures``); storing is keyed by chain key, so a task
  computed twice is stored once.

At most ``in_flight`` acquisitions are planned ahead of the results coming back, so a job
over thousands of acquisitions holds only a few frames in memory. One acquisition failing
(no calibration, a frame of the wrong size) is recorded and the job goes on.

:func:`process_many` runs a list of uids and returns their outcomes (no job row);
:mod:`rasterserver.processing_jobs` runs the same loop over a job's task rows.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import os
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from rasterserver.archive import Archive
from rasterserver.chain import DEFAULT_TARGET, Computation, Plan
from rasterserver.errors import RasterServerError
from rasterserver.pipeline import Pipeline, ProcessResult
from rasterserver.registry import Registry
from rasterserver.worker import work

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

#: From how many acquisitions a job asked for without ``--dask``/``--scheduler`` starts a
#: ``LocalCluster``; None: never. Measured on the 2-core development machine (BENCHMARKS.md,
#: "Processing jobs"): the coordinator's own work (planning, reading frames, writing derived
#: files, committing rows) is most of each acquisition's time, so two local worker processes
#: beside it were slower than computing in the coordinator. Change it when the coordinator's
#: share drops (issue 16, throughput).
LOCAL_CLUSTER_MIN: int | None = None

#: Acquisitions the in-process engine computes ahead of committing them.
IN_PROCESS_BATCH = 4
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


# --- engines ------------------------------------------------------------------------------------


class Engine:
    """Where :func:`rasterserver.pipeline.compute` runs; the coordinator loop is the same.

    Attributes
    ----------
    name : str
        ``"in-process"``, ``"local-cluster"`` or the scheduler's address (stored with a job).
    in_flight : int
        Acquisitions the coordinator keeps submitted ahead of the results.
    """

    name: str = ""
    in_flight: int = 1

    def submit(self, plan: Plan) -> cf.Future[Computation]:
        """Start computing what ``plan`` has not stored; a future of its :class:`Computation`."""
        raise NotImplementedError


class InProcess(Engine):
    """Compute here, at once: the future returned is already done.

    A few acquisitions are computed ahead of committing them (``in_flight``), so their rows
    go to the catalogue in one transaction.
    """

    name = "in-process"

    def __init__(self, pipeline: Pipeline, *, in_flight: int | None = None) -> None:
        self.pipeline = pipeline
        self.in_flight = max(1, in_flight or IN_PROCESS_BATCH)

    def submit(self, plan: Plan) -> cf.Future[Computation]:
        """Compute and write the files now; the future holds the result or the exception."""
        future: cf.Future[Computation] = cf.Future()
        try:
            future.set_result(
                work(plan, self.pipeline.archive.settings.archive,
                     registry=self.pipeline.registry)
            )
        except Exception as exc:
            future.set_exception(exc)
        return future


class OnDask(Engine):
    """Compute on the cluster of a Dask ``client`` (workers use their own plugin registry).

    Workers read the raw frame and write the derived files themselves
    (:func:`rasterserver.worker.work`): the archive must be at the same path on every worker
    (shared storage), ``root`` says where.

    Parameters
    ----------
    client : distributed.Client
        A connected client.
    name : str
        What to call the engine (``"local-cluster"`` or the scheduler's address).
    root : Path
        The archive root as the workers see it.
    in_flight : int, optional
        Acquisitions submitted ahead; by default four times the cluster's worker threads, so
        that every worker has the next acquisitions waiting while the coordinator commits a
        batch.
    """

    def __init__(
        self, client: Client, *, name: str, root: Path, in_flight: int | None = None
    ) -> None:
        self.client = client
        self.name = name
        self.root = str(root)
        if in_flight is None:
            threads = sum(client.nthreads().values()) or 1
            in_flight = max(8, 4 * threads)
        self.in_flight = max(1, in_flight)
        # concurrent.futures futures: the loop waits on them as on the in-process ones
        self._executor = client.get_executor(pure=False)

    def submit(self, plan: Plan) -> cf.Future[Computation]:
        """Send the plan (chain, keys, station data; no pixels) to a worker."""
        return self._executor.submit(work, plan, self.root)


def quiet_dask_logs() -> None:
    """Keep Dask's INFO lines (cluster started, worker joined, ...) off the user's terminal.

    Its warnings and errors still show. With ``--verbose`` (root logger at INFO) nothing is
    changed. Worker processes of a ``LocalCluster`` read the environment variable.
    """
    if logging.getLogger().isEnabledFor(logging.INFO):
        return
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    for name in ("distributed", "dask"):
        logging.getLogger(name).setLevel(logging.WARNING)
    try:
        import dask

        dask.config.set({"logging.distributed": "warning"})
    except ImportError:  # pragma: no cover - dask is a dependency
        pass


@contextmanager
def dask_client(*, scheduler: str | None = None, n_workers: int | None = None) -> Iterator[Client]:
    """A Dask client for the scheduler at ``scheduler``, or for a new ``LocalCluster``.

    Parameters
    ----------
    scheduler : str, optional
        Scheduler address (``tcp://host:8786``); a local cluster when None.
    n_workers : int, optional
        Worker processes of the local cluster (default: one per core).

    Yields
    ------
    distributed.Client
    """
    quiet_dask_logs()
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
    # a worker samples its own stack every 10 ms for the dashboard's profile, which this
    # cluster does not serve: a few percent of every core for nothing
    os.environ.setdefault("DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED", "False")
    # one thread per worker: the stages are numpy code that is fastest single-threaded
    # per frame, and parallel across frames
    with (
        LocalCluster(
            n_workers=n_workers or os.cpu_count() or 1,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def engine_name(
    count: int,
    *,
    dask: bool | None = None,
    scheduler: str | None = None,
    default_scheduler: str | None = None,
) -> str:
    """Which engine a job of ``count`` acquisitions runs on: ``"in-process"``,
    ``"local-cluster"`` or a scheduler address.

    An explicit ``scheduler`` wins; ``dask=False`` computes here; ``dask=True`` uses
    ``default_scheduler`` (``RASTERSERVER_DASK_SCHEDULER``) or a ``LocalCluster``. Unsaid
    (``dask=None``): one acquisition is computed here; more go to ``default_scheduler`` if
    one is set, else to a ``LocalCluster`` only from :data:`LOCAL_CLUSTER_MIN` acquisitions.
    """
    if scheduler:
        return scheduler
    if dask is False:
        return "in-process"
    if dask is True:
        return default_scheduler or "local-cluster"
    if count <= 1:
        return "in-process"
    if default_scheduler:
        return default_scheduler
    if LOCAL_CLUSTER_MIN is not None and count >= LOCAL_CLUSTER_MIN:
        return "local-cluster"
    return "in-process"


@contextmanager
def open_engine(
    name: str,
    pipeline: Pipeline,
    *,
    client: Client | None = None,
    n_workers: int | None = None,
    in_flight: int | None = None,
) -> Iterator[Engine]:
    """The engine called ``name`` (see :func:`engine_name`), started and stopped here.

    Parameters
    ----------
    name : str
        ``"in-process"``, ``"local-cluster"`` or a scheduler address.
    pipeline : Pipeline
        The coordinator's pipeline (the in-process engine uses its registry).
    client : distributed.Client, optional
        Use this client's cluster (``name`` is then only a label).
    n_workers : int, optional
        Workers of a local cluster.
    in_flight : int, optional
        Acquisitions submitted ahead on Dask.
    """
    root = pipeline.archive.settings.archive
    if client is not None:
        yield OnDask(client, name=name, root=root, in_flight=in_flight)
        return
    if name == "in-process":
        yield InProcess(pipeline, in_flight=in_flight)
        return
    scheduler = None if name == "local-cluster" else name
    with dask_client(scheduler=scheduler, n_workers=n_workers) as own:
        yield OnDask(own, name=name, root=root, in_flight=in_flight)


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
    reads the frame), the computing and the derived files on the engine
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

    def advance(task: _Task) -> None:
        # plan the task's next target: stored ones are committed here, the first that needs
        # computing goes to the engine
        while task.targets:
            target = task.targets.pop(0)
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
            item = next(source, None)
            if item is None:
                break
            index, uid = item
            begun.append(index)
            advance(_Task(index, uid, list(targets)))
            stopping = ask()
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
        results = pipeline.commit_many([(plan, computation) for _t, plan, computation in batch])
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
