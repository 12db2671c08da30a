"""Process many acquisitions: in this process, or on a Dask cluster.

Stages are pure, so only the computing is shipped: the driver (this process) plans each
acquisition (catalogue lookups, reading the raw frame or a stored intermediate result), sends
the input record, the resolved chain and the station data to a worker, and stores what comes
back (derived files, provenance rows). Workers never touch the archive or the catalogue, which
is what lets them run on machines that cannot reach either.

Where the work runs:

* ``dask=False``: one acquisition after the other, here.
* ``dask=True`` with a ``client``: that client's cluster.
* ``dask=True`` and ``RASTERSERVER_DASK_SCHEDULER`` (or ``scheduler``) set: that scheduler.
* ``dask=True`` otherwise: a ``LocalCluster`` with one single-threaded worker process per
  core, started and stopped around the job.

At most ``max_in_flight`` acquisitions are planned ahead of the results coming back, so a job
over thousands of acquisitions holds only a few frames in memory. One acquisition failing
(no calibration, a frame of the wrong size) is recorded and the job goes on.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from rasterserver.archive import Archive
from rasterserver.errors import RasterServerError
from rasterserver.pipeline import DEFAULT_TARGET, Pipeline, Plan, ProcessResult, compute
from rasterserver.registry import Registry

if TYPE_CHECKING:
    from distributed import Client

__all__ = ["JobOutcome", "Progress", "dask_client", "process_many"]

log = logging.getLogger(__name__)

#: Called with (done, total) after each acquisition.
Progress = Callable[[int, int], None]


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
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as client:
            yield client
        return
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
    max_in_flight: int = 16,
    progress: Progress | None = None,
    registry: Registry | None = None,
) -> list[JobOutcome]:
    """Process ``uids`` through the chain; stored results are reused, failures recorded.

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
        Compute on a Dask cluster (see the module docstring for which one).
    client : distributed.Client, optional
        Use this client (implies ``dask``).
    scheduler : str, optional
        Scheduler address; defaults to the archive settings' ``dask_scheduler``.
    n_workers : int, optional
        Workers of a local cluster started here.
    max_in_flight : int, optional
        Acquisitions planned but not yet stored, at most.
    progress : Progress, optional
        Called with (done, total) after each acquisition.
    registry : Registry, optional
        Where the driver finds plugins (workers use their own).

    Returns
    -------
    list of JobOutcome
        One per uid, in the order given.
    """
    pipeline = Pipeline(archive, registry=registry)
    targets = [until] if isinstance(until, str) else list(dict.fromkeys(until))
    options = {"chain": chain, "params": params, "calibration": calibration}
    total = len(uids)
    report = progress or (lambda _done, _total: None)
    report(0, total)
    if not (dask or client is not None):
        outcomes = []
        for uid in uids:
            outcome: JobOutcome | None = None
            for target in targets:
                try:
                    step = JobOutcome.done(pipeline.process(uid, until=target, **options))
                except Exception as exc:
                    step = JobOutcome.failed(uid, exc)
                outcome = step if outcome is None else outcome.then(step)
                if step.status == "failed":
                    break  # the next target would fail the same way (no frame, no calibration)
            assert outcome is not None
            outcomes.append(outcome)
            report(len(outcomes), total)
        return outcomes
    passes: list[list[JobOutcome]] = []
    for k, target in enumerate(targets):
        step_options = {**options, "until": target}

        def step_report(done: int, _total: int, k: int = k) -> None:
            report(min(total, (k * total + done) // len(targets)), total)

        if client is not None:
            passes.append(
                _on_dask(pipeline, client, uids, step_options, max_in_flight, step_report)
            )
            continue
        address = scheduler or archive.settings.dask_scheduler
        with dask_client(scheduler=address, n_workers=n_workers) as own:
            passes.append(_on_dask(pipeline, own, uids, step_options, max_in_flight, step_report))
    merged = passes[0]
    for later in passes[1:]:
        merged = [a.then(b) for a, b in zip(merged, later, strict=True)]
    return merged


def _on_dask(
    pipeline: Pipeline,
    client: Client,
    uids: Sequence[str],
    options: Mapping[str, Any],
    max_in_flight: int,
    report: Progress,
) -> list[JobOutcome]:
    from distributed import as_completed

    total = len(uids)
    outcomes: dict[str, JobOutcome] = {}
    pending = iter(uids)
    plans: dict[str, Plan] = {}
    uid_of: dict[str, str] = {}  # future key -> acquisition
    futures = as_completed()

    def finish(uid: str, outcome: JobOutcome) -> None:
        outcomes[uid] = outcome
        report(len(outcomes), total)

    def submit_next() -> bool:
        # plan until one acquisition needs computing (or none is left)
        for uid in pending:
            try:
                plan = pipeline.plan(uid, **options)
            except Exception as exc:
                finish(uid, JobOutcome.failed(uid, exc))
                continue
            if plan.input_record is None:  # everything stored already
                _commit(pipeline, plan, None, finish)
                continue
            future = client.submit(
                compute, plan.input_record, plan.to_compute, plan.context, pure=False
            )
            uid_of[future.key] = uid
            plans[uid] = plan
            futures.add(future)
            return True
        return False

    for _ in range(max(1, max_in_flight)):
        if not submit_next():
            break
    for future in futures:
        uid = uid_of.pop(future.key)
        plan = plans.pop(uid)
        try:
            computation = future.result()
        except Exception as exc:
            pipeline.fail(plan.run_id, exc)
            finish(uid, JobOutcome.failed(uid, exc))
        else:
            _commit(pipeline, plan, computation, finish)
        future.release()
        submit_next()
    return [outcomes[uid] for uid in uids]


def _commit(
    pipeline: Pipeline,
    plan: Plan,
    computation: Any,
    finish: Callable[[str, JobOutcome], None],
) -> None:
    try:
        result = pipeline.commit(plan, computation or pipeline.compute(plan))
    except Exception as exc:
        finish(plan.uid, JobOutcome.failed(plan.uid, exc))
    else:
        finish(plan.uid, JobOutcome.done(result))
