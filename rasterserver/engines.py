"""Where the chain of each acquisition runs: here (:class:`InProcess`) or on Dask (:class:`OnDask`).

The coordinator loop (:func:`rasterserver.jobs.run_tasks`) is the same for every engine; an
engine only runs :func:`rasterserver.worker.work` (read the frame, compute, write the derived
files) and hands back a future. :func:`engine_name` picks one for a job, :func:`open_engine`
starts and stops it, :func:`dask_client` connects to a scheduler or starts a ``LocalCluster``
with Dask's INFO logs kept off the terminal (:func:`quiet_dask_logs`).
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rasterserver.chain import Computation, Plan
from rasterserver.pipeline import Pipeline
from rasterserver.worker import work, work_batch

if TYPE_CHECKING:
    from distributed import Client

__all__ = [
    "CLIENT_CONFIG",
    "DASK_BATCH",
    "IN_PROCESS_BATCH",
    "LOCAL_CLUSTER_MIN",
    "LOCAL_WORKER_CONFIG",
    "Engine",
    "InProcess",
    "OnDask",
    "dask_client",
    "engine_name",
    "open_engine",
    "quiet_dask_logs",
]

log = logging.getLogger(__name__)

#: From how many acquisitions a job asked for without ``--dask``/``--scheduler`` starts a
#: ``LocalCluster`` (one single-threaded worker per core; only with two cores or more); None:
#: never. Measured on the 2-core development machine (BENCHMARKS.md, "Reprocessing
#: throughput", benchmarks/reprocess.py, 2026-11-24): 1,000 acquisitions took 140 s
#: in-process, 137 s on one local worker and 88 s on two (1.60x), and the cluster takes
#: ~5.5 s to start and import the plugins: it pays for itself from ~110 acquisitions, so
#: from 200 with room for a busier machine.
LOCAL_CLUSTER_MIN: int | None = 200

#: Dask settings of the workers of a ``LocalCluster`` (a nanny hands its process's Dask
#: configuration to the worker it spawns, so they are set here, not in the environment).
#: Measured on the 2-core machine (BENCHMARKS.md, "Reprocessing throughput"): with Dask's
#: defaults one worker spent 344 ms of CPU per acquisition, 195 of them in the kernel, against
#: ~100 in-process. ``MALLOC_TRIM_THRESHOLD_``, which Dask sets for every worker to give memory
#: back sooner, also switches off glibc's adaptive mmap threshold: every array above 128 KiB
#: is then mapped and unmapped afresh, and each first touch of its pages faults. The
#: statistical profiler samples the computing thread every 10 ms for a dashboard this cluster
#: does not serve. A real cluster's workers (``--scheduler``) take their own configuration:
#: docs/jobs.md and docker/ give the same two settings.
LOCAL_WORKER_CONFIG: dict[str, object] = {
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    "distributed.worker.profile.enabled": False,
}

#: Dask settings for the coordinator's client (and a local cluster's scheduler). Every batched
#: stream keeps its last ``low-level-log-length`` messages for debugging (1,000 by default):
#: with a job's tasks, each carrying eight plans, that held ~6 MB per 1,000 acquisitions in
#: the coordinator, growing until the cap at ~100 MB per stream (benchmarks/
#: coordinator_memory.py).
CLIENT_CONFIG: dict[str, object] = {
    "distributed.admin.low-level-log-length": 16,
}

#: Acquisitions to a Dask task (:func:`rasterserver.worker.work_batch`). Sixteen rather than
#: eight: the coordinator's CPU per acquisition 4.4-5.7 → 3.6-4.6 ms on two local workers
#: (BENCHMARKS.md, "Reprocessing throughput", 2026-11-27 (4)); a worker killed mid-task has
#: at most sixteen acquisitions redone, and the last task of a job may keep one worker busy
#: up to sixteen acquisitions' time (~1 s) after the other is done.
DASK_BATCH = 16

#: Acquisitions the in-process engine computes ahead of committing them (and plans in one
#: page, :meth:`rasterserver.pipeline.Pipeline.plan_many`).
IN_PROCESS_BATCH = 16


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
        """Start computing what ``plan`` has not stored; a future of its :class:`Computation`.

        The computation holds what was stored (its files), not the records: a job reports
        counts and reasons, and a record sent back from a worker costs both sides its bytes.
        """
        raise NotImplementedError

    def flush(self) -> None:
        """Start what :meth:`submit` may hold back; the coordinator calls it before waiting."""


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
                work(
                    plan,
                    self.pipeline.archive.settings.archive,
                    registry=self.pipeline.registry,
                    keep="none",
                )
            )
        except Exception as exc:
            future.set_exception(exc)
        return future


class OnDask(Engine):
    """Compute on the cluster of a Dask ``client`` (workers use their own plugin registry).

    Workers read the raw frame and write the derived files themselves
    (:func:`rasterserver.worker.work`): the archive must be at the same path on every worker
    (shared storage), ``root`` says where. Plans are sent :data:`DASK_BATCH` to a task
    (:func:`rasterserver.worker.work_batch`): a Dask task costs the coordinator and the
    scheduler milliseconds of their own, which a batch shares; :meth:`flush` sends a batch
    not yet full before the coordinator waits.

    Parameters
    ----------
    client : distributed.Client
        A connected client.
    name : str
        What to call the engine (``"local-cluster"`` or the scheduler's address).
    root : Path
        The archive root as the workers see it.
    in_flight : int, optional
        Acquisitions submitted ahead; by default three batches per worker thread, so that
        every worker has the next batch waiting while the coordinator commits rows.
    batch : int, optional
        Acquisitions to a task (default :data:`DASK_BATCH`).
    """

    def __init__(
        self,
        client: Client,
        *,
        name: str,
        root: Path,
        in_flight: int | None = None,
        batch: int | None = None,
    ) -> None:
        self.client = client
        self.name = name
        self.root = str(root)
        self.batch = max(1, batch or DASK_BATCH)
        if in_flight is None:
            threads = sum(client.nthreads().values()) or 1
            in_flight = max(8, 3 * self.batch * threads)
        self.in_flight = max(1, in_flight)
        self.batch = min(self.batch, self.in_flight)
        self._waiting: list[tuple[Plan, cf.Future[Computation]]] = []

    def submit(self, plan: Plan) -> cf.Future[Computation]:
        """Queue the plan (chain, keys, station data; no pixels) for a worker: sent with its
        batch when the batch is full or at :meth:`flush`."""
        future: cf.Future[Computation] = cf.Future()
        self._waiting.append((plan, future))
        if len(self._waiting) >= self.batch:
            self.flush()
        return future

    def flush(self) -> None:
        """Send the queued plans as one task."""
        if not self._waiting:
            return
        batch, self._waiting = self._waiting, []
        task = self.client.submit(
            work_batch, [plan for plan, _f in batch], self.root, keep="none", pure=False
        )

        def settle(task: Any) -> None:
            # on the client's event loop: hand each acquisition its own outcome
            try:
                outcomes = task.result()
            except BaseException as exc:  # the task itself failed (a worker lost too often)
                outcomes = [exc] * len(batch)
            for (_plan, future), outcome in zip(batch, outcomes, strict=True):
                if future.done():  # cancelled by the coordinator meanwhile
                    continue
                if isinstance(outcome, BaseException):
                    future.set_exception(outcome)
                else:
                    future.set_result(outcome)

        task.add_done_callback(settle)


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
    import dask
    from distributed import Client, LocalCluster

    if scheduler:
        with dask.config.set(CLIENT_CONFIG), Client(scheduler) as client:
            yield client
        return
    # one thread per worker: the stages are numpy code that is fastest single-threaded
    # per frame, and parallel across frames
    with (
        dask.config.set({**LOCAL_WORKER_CONFIG, **CLIENT_CONFIG}),
        LocalCluster(
            n_workers=n_workers or os.cpu_count() or 1,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
        ) as cluster,
        Client(cluster) as client,
    ):
        from rasterserver.worker_logs import QuietClosingHeartbeat

        client.register_plugin(QuietClosingHeartbeat())
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
    one is set, else to a ``LocalCluster`` from :data:`LOCAL_CLUSTER_MIN` acquisitions on a
    machine of two cores or more.
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
    if (
        LOCAL_CLUSTER_MIN is not None
        and count >= LOCAL_CLUSTER_MIN
        and (os.cpu_count() or 1) >= 2  # one worker on one core gains nothing
    ):
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
