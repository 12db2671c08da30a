"""Processing jobs that survive their process: catalogue rows, paused, cancelled, resumed.

A job is created (:func:`create_job`) with its selection, its chain (plugins, versions,
parameters, calibration) and one task row per acquisition the selection resolved to, in one
transaction: it exists whole or not at all. A coordinator (:func:`run_job`: the
``rasterserver process`` or ``jobs resume`` command, or a thread of the HTTP server) takes the
job by writing itself as its ``runner``, runs the pending tasks through the one loop of
:func:`rasterserver.jobs.run_tasks`, and marks the tasks of each batch done with the job's
counts in one transaction after the batch's results are committed.

Why nothing is lost or duplicated:

* a coordinator killed mid-job leaves the job ``running`` under a runner that is gone; it is
  reported as interrupted and :func:`run_job` (``jobs resume``) takes it again and runs the
  tasks still ``pending``;
* a task whose results were committed but not yet marked done is redone: every stage result
  is keyed by its chain key (unique per acquisition), so the redo finds them stored and
  computes nothing;
* a worker killed mid-task: Dask reruns the task elsewhere; the coordinator stores the one
  result it receives.

Pause and cancel are requests written to the row (:func:`pause_job`, :func:`cancel_job`) from
any process; the coordinator reads the state between tasks (and at least every half second)
and stops: after the tasks in flight are stored (paused), or dropping them (cancelled).
"""

from __future__ import annotations

import datetime as dt
import getpass
import logging
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, cast

from sqlalchemy import Table, bindparam, func, or_, select, update

from rasterserver.archive import Archive
from rasterserver.catalog.job_models import JOB_STATES, ProcessingJob, ProcessingTask
from rasterserver.errors import ConflictError, InputError, NotFoundError, RasterServerError
from rasterserver.job_selection import Selection, resolve_selection
from rasterserver.job_status import JobStatus, job_outcomes, job_status
from rasterserver.jobs import JobOutcome, StopReason, engine_name, open_engine, run_tasks
from rasterserver.pipeline import DEFAULT_TARGETS, Pipeline, resolve_chain
from rasterserver.registry import Registry
from rasterserver.runner import current_runner, describe_runner, runner_gone

if TYPE_CHECKING:
    from sqlalchemy.engine import CursorResult

__all__ = [
    "JobStatus",
    "Selection",
    "cancel_job",
    "create_job",
    "find_job",
    "job_outcomes",
    "job_status",
    "list_jobs",
    "pause_job",
    "resolve_selection",
    "run_job",
]

log = logging.getLogger(__name__)

#: Tasks read from the catalogue at a time by a coordinator (memory stays bounded).
_PAGE = 500
#: Seconds between two reads of the job's state by a coordinator (pause, cancel).
_POLL_S = 0.25


_TASKS = cast(Table, ProcessingTask.__table__)
#: A finished task's outcome, only if it is still pending: each task is counted once, whatever
#: happens (a Core UPDATE run once for many tasks; the ORM's would check each row's objects).
_MARK_TASK = (
    update(_TASKS)
    .where(_TASKS.c.job_id == bindparam("b_job"), _TASKS.c.position == bindparam("b_position"),
           _TASKS.c.state == "pending")
    .values(state=bindparam("b_state"), computed=bindparam("b_computed"),
            reused=bindparam("b_reused"), reason=bindparam("b_reason"),
            error=bindparam("b_error"), exit_code=bindparam("b_exit_code"),
            finished_at=bindparam("b_finished_at"))
)


def _rowcount(result: object) -> int:
    """Rows an UPDATE changed: Session.execute is typed Result, but for an UPDATE it gives a
    CursorResult, which has the count."""
    return cast("CursorResult[Any]", result).rowcount


def _now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


# --- creating and finding jobs -------------------------------------------------------------------


def create_job(
    archive: Archive,
    selection: Selection,
    *,
    chain: Mapping[str, str] | None = None,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    calibration: tuple[str, int | None] | None = None,
    targets: Sequence[str] = DEFAULT_TARGETS,
    owner: str | None = None,
    origin: str = "cli",
    registry: Registry | None = None,
) -> tuple[ProcessingJob, int]:
    """Store a ``queued`` job over the acquisitions ``selection`` resolves to, with its tasks.

    The chain is resolved for each target first (an unknown plugin or stage is refused
    before anything is stored), and stored with the plugin versions and parameters.

    Parameters
    ----------
    archive : Archive
        The archive.
    selection : Selection
        What to process.
    chain, params, calibration
        As for :meth:`rasterserver.pipeline.Pipeline.plan`.
    targets : sequence of str, optional
        Last stage kinds (default: the mesh and the analysis).
    owner : str, optional
        Who started it (default: this process's user).
    origin : str, optional
        ``"cli"`` or ``"http"``.
    registry : Registry, optional
        Where plugins are found.

    Returns
    -------
    (ProcessingJob, int)
        The job row and its number of tasks (0: nothing selected, and nothing stored).
    """
    targets = list(dict.fromkeys(targets)) or list(DEFAULT_TARGETS)
    resolved = {
        target: [
            {**step.describe(), "params": step.params}
            for step in resolve_chain(chain, params=params, until=target, registry=registry)
        ]
        for target in targets
    }
    if calibration is not None:
        archive.calibration(*calibration)  # unknown station or version: refused now
    acquisitions = resolve_selection(archive, selection)
    job = ProcessingJob(
        id=uuid.uuid4().hex,
        origin=origin,
        owner=(owner or _user())[:100],
        selection=selection.to_dict(),
        chain={
            "chain": dict(chain or {}),
            "params": {k: dict(v) for k, v in (params or {}).items()},
            "calibration": list(calibration) if calibration else None,
            "resolved": resolved,
        },
        targets=targets,
        engine="",
        state="queued",
        total=len(acquisitions),
        done=0,
        failed=0,
        # the creating process: a job queued by a server that then stopped shows interrupted
        runner=current_runner(),
        error="",
        resumed_count=0,
        created_at=_now(),
    )
    if not acquisitions:
        return job, 0
    with archive.session() as s:
        s.add(job)
        s.flush()
        # one INSERT of many rows: a job of 10,000 acquisitions is created in one go
        s.execute(
            # a declarative class's __table__ is typed FromClause; this one is a Table
            cast(Table, ProcessingTask.__table__).insert(),
            [
                {
                    "job_id": job.id, "position": position, "uid": uid,
                    "acquisition_id": acquisition_id, "state": "pending", "attempts": 0,
                    "computed": 0, "reused": 0, "reason": "", "error": "", "exit_code": 0,
                }
                for position, (uid, acquisition_id) in enumerate(acquisitions)
            ],
        )
    return job, len(acquisitions)


def _user() -> str:
    try:
        return getpass.getuser()
    except Exception:  # no user name in a bare container: say so rather than fail
        return "unknown"


def find_job(archive: Archive, job_id: str) -> ProcessingJob:
    """The job ``job_id``, or one whose id starts with it (at least 6 characters, unique).

    Raises
    ------
    NotFoundError
        No such job, or the prefix is too short or names several.
    """
    job_id = job_id.strip().lower()
    with archive.session() as s:
        job = s.get(ProcessingJob, job_id) if job_id else None
        if job is None and 6 <= len(job_id) < 32 and job_id.isalnum():
            matches = list(
                s.scalars(select(ProcessingJob).where(ProcessingJob.id.like(f"{job_id}%")).limit(2))
            )
            if len(matches) > 1:
                raise NotFoundError(f"job id {job_id!r} is ambiguous: give more of it")
            job = matches[0] if matches else None
    if job is None:
        raise NotFoundError(f"unknown job {job_id!r}: see `rasterserver jobs list`")
    return job


def list_jobs(
    archive: Archive, *, state: str | None = None, limit: int = 100, offset: int = 0
) -> list[ProcessingJob]:
    """Jobs, newest first, optionally of one stored state.

    Raises
    ------
    InputError
        An unknown state.
    """
    if state is not None and state not in JOB_STATES:
        raise InputError(f"unknown job state {state!r}; states: {', '.join(JOB_STATES)}")
    query = select(ProcessingJob).order_by(ProcessingJob.created_at.desc(), ProcessingJob.id)
    if state is not None:
        query = query.where(ProcessingJob.state == state)
    with archive.session() as s:
        return list(s.scalars(query.limit(limit).offset(offset)))


# --- pause, cancel -------------------------------------------------------------------------------


def pause_job(archive: Archive, job_id: str) -> ProcessingJob:
    """Ask job ``job_id`` to stop after the acquisitions in flight; it can be resumed.

    Raises
    ------
    NotFoundError
        Unknown job.
    ConflictError
        The job is not queued or running.
    """
    return _request(archive, job_id, "paused", ("queued", "running"))


def cancel_job(archive: Archive, job_id: str) -> ProcessingJob:
    """Stop job ``job_id`` for good: what is in flight is dropped, pending tasks never run.

    Results already stored stay (they are valid, and a later job reuses them).

    Raises
    ------
    NotFoundError
        Unknown job.
    ConflictError
        The job is finished or cancelled already.
    """
    return _request(archive, job_id, "cancelled", ("queued", "running", "paused", "failed"))


def _request(archive: Archive, job_id: str, state: str, allowed: Sequence[str]) -> ProcessingJob:
    job = find_job(archive, job_id)
    if job.state == "failed" and state == "cancelled" and job.done + job.failed >= job.total:
        allowed = ()  # a finished job is not cancelled after the fact
    with archive.session() as s:
        values: dict[str, Any] = {"state": state}
        if state == "cancelled":
            values["finished_at"] = _now()
        changed = _rowcount(s.execute(
            update(ProcessingJob)
            .where(ProcessingJob.id == job.id, ProcessingJob.state.in_(allowed))
            .values(**values)
        ))
    if not changed:
        current = find_job(archive, job.id)
        verb = "pause" if state == "paused" else "cancel"
        raise ConflictError(
            f"job {job.id} is {current.state}: only a {' or '.join(allowed) or 'running'} job "
            f"can be {state}" + (f" (nothing to {verb})" if current.state == state else "")
        )
    return find_job(archive, job.id)


# --- running -------------------------------------------------------------------------------------


def _take(archive: Archive, job_id: str, engine: str, *, force: bool) -> ProcessingJob:
    """Make this process the job's coordinator, or say why it cannot be."""
    job = find_job(archive, job_id)
    left = job.total - job.done - job.failed
    if job.state == "cancelled":
        raise ConflictError(f"job {job.id} was cancelled; start a new job to process its "
                            "acquisitions")
    if job.state == "done" or (job.state == "failed" and left == 0):
        raise ConflictError(
            f"job {job.id} is finished ({job.done} done, {job.failed} failed): nothing left to "
            "resume; process the failed acquisitions again with a new job"
        )
    if job.state in ("running", "queued") and job.runner:
        mine = job.runner == current_runner()
        if not (mine or force or runner_gone(job.runner)):
            raise ConflictError(
                f"job {job.id} is {job.state} in process {describe_runner(job.runner)}, which "
                "is alive or on another host; if it has stopped, resume with --force"
            )
    now = _now()
    with archive.session() as s:
        changed = _rowcount(s.execute(
            update(ProcessingJob)
            .where(ProcessingJob.id == job.id, ProcessingJob.state == job.state,
                   ProcessingJob.runner == job.runner)
            .values(
                state="running", runner=current_runner(), engine=engine, error="",
                started_at=func.coalesce(ProcessingJob.started_at, now),
                resumed_at=now, resumed_count=ProcessingJob.done + ProcessingJob.failed,
                progress_at=now, finished_at=None,
            )
        ))
    if not changed:  # another coordinator took it in between
        raise ConflictError(f"job {job.id} was taken by another process meanwhile")
    return find_job(archive, job.id)


def _check_chain(job: ProcessingJob, registry: Registry | None) -> dict[str, Any]:
    """The job's plan options, after checking its plugins are still the versions it began
    with (results of a job are one computation, not a mixture)."""
    chain = job.chain
    options: dict[str, Any] = {
        "chain": chain.get("chain") or None,
        "params": chain.get("params") or None,
        "calibration": tuple(chain["calibration"]) if chain.get("calibration") else None,
    }
    for target, stored in chain.get("resolved", {}).items():
        now = resolve_chain(options["chain"], params=options["params"], until=target,
                            registry=registry)
        then = [(s["plugin"], s["version"], s["params_hash"]) for s in stored]
        here = [(s.plugin, s.version, s.params_hash) for s in now]
        if then != here:
            changed = sorted({f"{p} {v}" for p, v, _h in here} - {f"{p} {v}" for p, v, _h in then})
            raise ConflictError(
                f"job {job.id} was created with other plugin versions or defaults than are "
                f"installed now ({', '.join(changed) or 'parameters'}); start a new job"
            )
    return options


def run_job(
    archive: Archive,
    job_id: str,
    *,
    dask: bool | None = None,
    scheduler: str | None = None,
    n_workers: int | None = None,
    force: bool = False,
    progress: Callable[[JobStatus], None] | None = None,
    registry: Registry | None = None,
    client: Any = None,
) -> JobStatus:
    """Run (or resume) job ``job_id`` here until its tasks are done, or it is paused or
    cancelled.

    Parameters
    ----------
    archive : Archive
        The archive.
    job_id : str
        The job (or a unique prefix of its id).
    dask, scheduler, n_workers
        Where to compute: see :func:`rasterserver.jobs.engine_name`.
    force : bool, optional
        Take a job whose coordinator cannot be checked (another host) as stopped.
    progress : callable, optional
        Called with the job's status after each batch of tasks (and once at the start).
    registry : Registry, optional
        Where plugins are found.
    client : distributed.Client, optional
        Compute on this client's cluster.

    Returns
    -------
    JobStatus
        The job at the end: ``done``, ``failed``, ``paused`` or ``cancelled``.

    Raises
    ------
    NotFoundError
        Unknown job.
    ConflictError
        The job is finished or cancelled, runs in a live process, or was created with other
        plugin versions than are installed.
    KeyboardInterrupt
        After pausing the job (it can be resumed).
    """
    job = find_job(archive, job_id)
    options = _check_chain(job, registry)
    left = job.total - job.done - job.failed
    name = engine_name(left, dask=dask if client is None else True, scheduler=scheduler,
                       default_scheduler=archive.settings.dask_scheduler)
    job = _take(archive, job.id, name if client is None else "client", force=force)
    me = job.runner
    pipeline = Pipeline(archive, registry=registry)
    last_poll = 0.0
    counts = {"done": job.done, "failed": job.failed}
    resumed = (job.resumed_at, job.resumed_count)

    def report() -> None:
        if progress is None:
            return
        now = _now()
        job.done, job.failed, job.progress_at = counts["done"], counts["failed"], now
        job.resumed_at, job.resumed_count = resumed
        progress(job_status(archive, job))

    def started(positions: list[int]) -> None:
        with archive.session() as s:
            s.execute(
                update(ProcessingTask)
                .where(ProcessingTask.job_id == job.id, ProcessingTask.position.in_(positions))
                .values(attempts=ProcessingTask.attempts + 1)
            )

    def pending() -> Iterator[tuple[int, str]]:
        after = -1
        while True:
            with archive.session() as s:
                rows = list(
                    s.execute(
                        select(ProcessingTask.position, ProcessingTask.uid)
                        .where(ProcessingTask.job_id == job.id,
                               ProcessingTask.state == "pending",
                               ProcessingTask.position > after)
                        .order_by(ProcessingTask.position)
                        .limit(_PAGE)
                    )
                )
            if not rows:
                return
            yield from rows
            after = rows[-1][0]

    ended: list[tuple[int, JobOutcome]] = []

    def finished(position: int, outcome: JobOutcome) -> None:
        ended.append((position, outcome))

    def flush() -> None:
        # the tasks whose results the loop just committed, in one transaction: a task is
        # marked after its results, so a kill in between only makes it redone (and reused)
        if not ended:
            return
        now = _now()
        added = {"done": 0, "failed": 0}
        with archive.session() as s:
            for state in added:
                rows = [
                    {"b_job": job.id, "b_position": position, "b_state": state,
                     "b_computed": outcome.computed, "b_reused": outcome.reused,
                     "b_reason": outcome.reason[:10_000], "b_error": outcome.error[:10_000],
                     "b_exit_code": outcome.exit_code, "b_finished_at": now}
                    for position, outcome in ended
                    if ("done" if outcome.status == "done" else "failed") == state
                ]
                if rows:  # one statement for all (the count is the sum over the rows)
                    added[state] = _rowcount(s.execute(_MARK_TASK, rows))
            if added["done"] or added["failed"]:
                s.execute(
                    update(ProcessingJob)
                    .where(ProcessingJob.id == job.id)
                    .values(done=ProcessingJob.done + added["done"],
                            failed=ProcessingJob.failed + added["failed"], progress_at=now)
                )
        ended.clear()
        for state, count in added.items():
            counts[state] += count
        report()

    def stop() -> StopReason:
        nonlocal last_poll
        if time.monotonic() - last_poll < _POLL_S:
            return None
        last_poll = time.monotonic()
        with archive.session() as s:
            state, runner = s.execute(
                select(ProcessingJob.state, ProcessingJob.runner)
                .where(ProcessingJob.id == job.id)
            ).one()
        if state == "cancelled":
            return "cancelled"
        if state != "running" or runner != me:
            return "paused"  # paused, or taken over (--force elsewhere): let go
        return None

    report()
    try:
        with open_engine(name, pipeline, client=client, n_workers=n_workers) as engine:
            stopped = run_tasks(pipeline, pending(), engine=engine, finished=finished,
                                targets=job.targets, options=options, stop=stop, flush=flush,
                                started=started)
    except KeyboardInterrupt:
        _finish(archive, job.id, me, state="paused")
        raise
    except Exception as exc:
        # the job as a whole failed (the catalogue went away, a bug): its pending tasks stay
        # and can be resumed
        message = str(exc) if isinstance(exc, RasterServerError) else (
            f"{type(exc).__name__}: {exc}")
        _finish(archive, job.id, me, state="failed", error=message[:2000])
        raise
    if stopped is None:
        with archive.session() as s:
            done, failed, total = s.execute(
                select(ProcessingJob.done, ProcessingJob.failed, ProcessingJob.total)
                .where(ProcessingJob.id == job.id)
            ).one()
        _finish(archive, job.id, me, state="done" if failed == 0 and done == total
                else "failed")
    return job_status(archive, find_job(archive, job.id), failures=20)


def _finish(archive: Archive, job_id: str, runner: str, *, state: str, error: str = "") -> None:
    """Store the job's end state if this process still runs it."""
    try:
        with archive.session() as s:
            s.execute(
                update(ProcessingJob)
                .where(ProcessingJob.id == job_id, ProcessingJob.runner == runner,
                       or_(ProcessingJob.state == "running", ProcessingJob.state == "queued"))
                .values(state=state, error=error,
                        finished_at=None if state == "paused" else _now())
            )
    except Exception:  # the original error matters more
        log.exception("could not record the end of job %s", job_id)
