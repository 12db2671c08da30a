"""The work of one acquisition where it is computed: read the frame, run the chain, write files.

:func:`work` is what an engine runs (:mod:`rasterserver.jobs`), in the coordinator process or
on a Dask worker with the archive on shared storage. It needs no catalogue:

* the raw frame is read by the worker itself, read-only and SHA-256 verified
  (:meth:`rasterserver.store.raw.RawStore.read`), so frames do not travel through the
  coordinator;
* each computed record is written durably to the derived store under its chain-key name
  (unique per computation, so two workers computing the same thing publish one file and the
  second adopts it); the acquisition's shard folder, which holds all its results, is fsynced
  once after the last file rather than once per file;
* what comes back is small: paths, checksums, timings, and the final record only when asked.

The coordinator then commits the catalogue rows (in batches, :meth:`rasterserver.pipeline.
Pipeline.commit_many`). A row is committed only after :func:`work` returned, so it never
names a file that is not on disk; a worker killed before returning leaves at most files
without rows, which the rerun adopts (``verify`` reports them as orphaned meanwhile).
"""

from __future__ import annotations

import socket
from pathlib import Path

from rasterserver.chain import Computation, Plan, compute
from rasterserver.errors import IntegrityError, NotFoundError
from rasterserver.records import Image, Record
from rasterserver.registry import Registry, get_registry
from rasterserver.store.derived import AREA, DerivedStore, StoredBase
from rasterserver.store.pending import PendingFiles
from rasterserver.store.raw import RawStore

__all__ = ["input_record", "work", "work_batch"]


def input_record(plan: Plan, root: Path, derived: DerivedStore) -> Record:
    """The record the plan's first step to compute takes: given, the raw frame, or the stored
    result before it.

    Raises
    ------
    NotFoundError, IntegrityError
        The frame or the stored result is missing or altered.
    """
    if plan.input_record is not None:
        return plan.input_record
    if plan.first == 0:
        # read-only, SHA-256 verified against the file: the raw frame is never touched
        pixels = RawStore(root).read(plan.uid, plan.frame_index)
        return Image(pixels, role=plan.frame_role)
    previous = plan.cached[plan.first - 1]
    assert previous is not None
    try:
        return derived.read(previous.store_path, expected_checksum=previous.output_checksum)
    except NotFoundError:
        raise IntegrityError(
            f"stored result {previous.store_path} is missing; run `rasterserver verify`"
        ) from None


def work(
    plan: Plan,
    root: Path | str,
    *,
    registry: Registry | None = None,
    keep: str = "final",
    pending: PendingFiles | None = None,
) -> Computation:
    """Compute the steps of ``plan`` without stored results and store them durably.

    Parameters
    ----------
    plan : Plan
        From :meth:`rasterserver.pipeline.Pipeline.plan`.
    root : Path or str
        The archive root (the folder holding ``raw/`` and ``derived/``), as this process
        sees it.
    registry : Registry, optional
        Where plugins are found; this process's own by default (a worker's).
    keep : {"final", "all", "none"}, optional
        Which records to send back besides their stored form: the last one (what
        ``process`` shows), every one, or none.
    pending : PendingFiles, optional
        Leave the files to it (see :func:`work_batch`): they are durable and published only
        after its :meth:`~rasterserver.store.pending.PendingFiles.publish`.

    Returns
    -------
    Computation
        ``stored`` holds each computed step's :class:`~rasterserver.store.derived.
        StoredResult`; ``records`` what ``keep`` asks for.
    """
    registry = registry or get_registry()
    root = Path(root)
    derived = DerivedStore(root, resolve=registry.record_type)
    if plan.first >= len(plan.steps):
        return Computation({}, {}, socket.gethostname())
    record = input_record(plan, root, derived)
    input_checksum = plan.input_checksum or record.content_hash()
    computation = compute(record, plan.to_compute, plan.context, registry=registry)
    store_computed(derived, plan, computation, input_checksum, input_record=record,
                   pending=pending)
    if keep != "all":
        last = plan.steps[-1].kind
        computation.records = (
            {last: computation.records[last]} if keep == "final" and plan.steps else {}
        )
    return computation


def work_batch(
    plans: list[Plan], root: Path | str, *, keep: str = "final"
) -> list[Computation | Exception]:
    """:func:`work` on each of ``plans``, in order: one Dask task for several acquisitions.

    A task costs the coordinator and the scheduler a few milliseconds whatever it computes;
    several acquisitions to a task share that cost. One acquisition's failure is returned in
    its place (as its exception) and does not stop the others. A worker killed mid-batch has
    the whole batch redone elsewhere; the files already written are adopted (their names are
    their chain keys), so redoing is idempotent.

    The files of the whole batch are made durable together, with two syncs of the
    filesystem rather than one fsync per file and folder
    (:class:`~rasterserver.store.pending.PendingFiles`), before this returns: an
    acquisition whose files could not be made durable or published is reported failed.

    Parameters
    ----------
    plans : list of Plan
        From :meth:`rasterserver.pipeline.Pipeline.plan`.
    root : Path or str
        The archive root as this process sees it.
    keep : {"final", "all", "none"}, optional
        As in :func:`work`. A job needs none of the records back (only what was stored):
        ``"none"`` spares the worker and the coordinator sending each acquisition's mesh
        (1.6 MB for a 604x576 frame) over the network.

    Returns
    -------
    list of Computation or Exception
        One per plan.
    """
    out: list[Computation | Exception] = []
    with PendingFiles(Path(root) / AREA) as pending:
        for plan in plans:
            try:
                out.append(work(plan, root, keep=keep, pending=pending))
            except Exception as exc:  # reported for this acquisition alone
                out.append(exc)
        errors = pending.publish()
    return [errors.get(plan.uid, outcome) if isinstance(outcome, Computation) else outcome
            for plan, outcome in zip(plans, out, strict=True)]


def store_computed(
    derived: DerivedStore,
    plan: Plan,
    computation: Computation,
    input_checksum: str,
    *,
    input_record: Record | None = None,
    pending: PendingFiles | None = None,
) -> None:
    """Write each computed step of ``plan`` not yet in ``computation.stored``, durably.

    Each result names the stored record it was computed from as its base, so that the fields
    it passes on unchanged are stored once (:class:`~rasterserver.store.derived.StoredBase`).

    Parameters
    ----------
    derived : DerivedStore
        Where the files go.
    plan : Plan
        The plan computed.
    computation : Computation
        Its records; ``stored`` gains each file written with the input checksum it was
        computed from.
    input_checksum : str
        The checksum of the plan's input record (the first step's input).
    input_record : Record, optional
        That record (``plan.input_record`` when not given): a stored result's fields are
        inherited by the first step's result; a raw frame's are not.
    pending : PendingFiles, optional
        Where the files are left to be made durable (see :func:`work_batch`).
    """
    if all(step.kind in computation.stored for step in plan.to_compute):
        return
    record = input_record if input_record is not None else plan.input_record
    previous = plan.cached[plan.first - 1] if plan.first > 0 else None
    base = (
        StoredBase(previous.store_path, record, input_checksum)
        if previous is not None and record is not None and not isinstance(record, Image)
        else None
    )
    for step, key in zip(plan.to_compute, plan.keys[plan.first :], strict=True):
        output = computation.records.get(step.kind)
        if step.kind in computation.stored:
            stored = computation.stored[step.kind][0]
            input_checksum = stored.output_checksum
            base = StoredBase(stored.path, output, input_checksum) if output is not None else None
            continue
        assert output is not None
        written = derived.write(
            plan.uid,
            output,
            stage=step.kind,
            plugin=step.plugin,
            plugin_version=step.version,
            params=step.params,
            params_hash=step.params_hash,
            chain_key=key,
            input_checksum=input_checksum,
            sync_dir=False,
            base=base,
            pending=pending,
        )
        computation.stored[step.kind] = (written, input_checksum)
        input_checksum = written.output_checksum
        base = StoredBase(written.path, output, input_checksum)
    # every result of the acquisition is in its one shard folder: one fsync makes the names
    # durable, before the coordinator may commit a row naming them
    if pending is None or not pending.deferring:
        derived.sync(plan.uid)
