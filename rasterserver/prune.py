"""Removing derived results that no kept chain needs, crash-safe; raw frames are never touched.

What is kept
------------
A result is kept when it lies on the path of a *kept chain* for its acquisition, or when a
kept result refers to it. The kept chains are:

* the **default chain**: the installed plugins at their installed versions with default
  parameters, up to every stage kind (so ``process --until points`` results are kept too);
* every chain given with ``--keep CHAIN`` (:mod:`rasterserver.chain_spec`), up to every kind;
* the chains of the ``keep_jobs`` newest processing jobs (their stored resolved chains, with
  versions and parameters hashes), up to the job's targets.

For each acquisition and kept chain, the *newest* matching path is kept (an older result of
the same chain under another calibration is not). Every comparison and asymmetry result is
kept (:mod:`rasterserver.stored_comparison`), so are the results they were computed from
(``stage_result_input``), and every ancestor (``parent_id``) of a kept result: a result that
a stored analysis or comparison refers to is never removed. The raw store is never read or
written; only files under the derived area named by removed rows are deleted.

Crash safety
------------
A catalogue row must never point at a missing file. The rows are deleted first, children
before parents, in one transaction; the files after the commit, each only if no row names it
any more (a file shared by several results goes with the last of them). Killed between the
commit and the deletions, the archive holds files without rows: ``rasterserver verify``
reports them as orphaned, which is harmless (a computation of the same chain key adopts its
file; ``verify --repair`` moves the rest to its quarantine). Pruning while a pipeline run is
in progress is refused: a run may be about to reuse a result being removed.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy import delete, select

from rasterserver.archive import Archive
from rasterserver.catalog.job_models import ProcessingJob
from rasterserver.catalog.models import Acquisition, PipelineRun, StageResult, StageResultInput
from rasterserver.chain_spec import ChainSpec, ResultRow, StepPattern, match_path, result_rows
from rasterserver.errors import ConflictError, InputError
from rasterserver.registry import Registry, get_registry
from rasterserver.store.derived import AREA as DERIVED_AREA

__all__ = ["PrunePlan", "PruneReport", "kept_chains", "plan_prune", "run_prune"]

log = logging.getLogger(__name__)

#: Stage kinds whose results are always kept (with what they were computed from).
ALWAYS_KEPT = ("comparison", "asymmetry")
_PAGE = 500


@dataclass
class KeptChain:
    """One kept chain: where it comes from and its step patterns per target."""

    source: str
    targets: dict[str, list[StepPattern]]


@dataclass
class PrunePlan:
    """What :func:`run_prune` would remove.

    Attributes
    ----------
    chains : list of str
        The kept chains, described.
    results : int
        Stored results in the catalogue.
    kept : int
        Results kept.
    remove : list of (int, str, int)
        ``(result id, store path, depth)`` of the results to remove (depth: 0 for a chain's
        first stage).
    files : dict of str to int
        Files to delete (no kept result names them) with their sizes in bytes.
    per_stage : dict of str to int
        Results to remove per stage kind.
    """

    chains: list[str] = field(default_factory=list)
    results: int = 0
    kept: int = 0
    remove: list[tuple[int, str, int]] = field(default_factory=list)
    files: dict[str, int] = field(default_factory=dict)
    per_stage: dict[str, int] = field(default_factory=dict)

    @property
    def bytes(self) -> int:
        """Bytes the files to delete take."""
        return sum(self.files.values())

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no list of files)."""
        return {"kept_chains": self.chains, "results": self.results, "kept": self.kept,
                "remove": len(self.remove), "files": len(self.files), "bytes": self.bytes,
                "per_stage": self.per_stage}


@dataclass
class PruneReport:
    """What :func:`run_prune` did."""

    rows_removed: int = 0
    files_removed: int = 0
    bytes_freed: int = 0
    files_missing: int = 0
    files_still_used: int = 0

    def to_dict(self) -> dict[str, int]:
        """JSON-ready."""
        return dict(self.__dict__)


def _reachable_kinds(registry: Registry) -> list[str]:
    from rasterserver.pipeline import resolve_chain

    kinds = []
    for kind in registry.stage_kinds():
        try:
            resolve_chain(None, until=kind, registry=registry)
        except Exception:  # a kind that takes another input (a comparison): not a chain
            continue
        kinds.append(kind)
    return kinds


def kept_chains(
    archive: Archive,
    keep: Sequence[ChainSpec] = (),
    *,
    keep_jobs: int = 1,
    registry: Registry | None = None,
) -> list[KeptChain]:
    """The kept chains (see the module docstring) as step patterns.

    Raises
    ------
    InputError, NotFoundError
        A ``--keep`` chain that does not resolve.
    """
    registry = registry or get_registry()
    kinds = _reachable_kinds(registry)
    chains: list[KeptChain] = []
    for spec in [ChainSpec(), *keep]:
        targets = {}
        for kind in kinds:
            try:
                targets[kind] = spec.patterns(kind, registry=registry)
            except InputError:
                if spec.stages or spec.params or spec.versions:
                    continue  # the spec names a stage not on the way to this kind
                raise
        if not targets:
            raise InputError(f"--keep {spec.text!r} is a chain to no stage kind")
        chains.append(KeptChain("default chain" if spec.text == "default" else spec.text,
                                targets))
    if keep_jobs > 0:
        with archive.session() as s:
            jobs = list(s.scalars(select(ProcessingJob).order_by(
                ProcessingJob.created_at.desc()).limit(keep_jobs)))
        for job in jobs:
            resolved = (job.chain or {}).get("resolved", {})
            targets = {
                target: [StepPattern(step["stage"], step["plugin"], str(step["version"]),
                                     step["params_hash"]) for step in steps]
                for target, steps in resolved.items()
            }
            if targets:
                chains.append(KeptChain(f"job {job.id[:8]}", targets))
    return chains


def _depths(rows: Iterable[ResultRow]) -> dict[int, int]:
    by_id = {row.id: row for row in rows}
    depth: dict[int, int] = {}

    def of(row: ResultRow) -> int:
        if row.id not in depth:
            parent = by_id.get(row.parent_id) if row.parent_id is not None else None
            depth[row.id] = 0 if parent is None else of(parent) + 1
        return depth[row.id]

    for row in by_id.values():
        of(row)
    return depth


def plan_prune(
    archive: Archive,
    keep: Sequence[ChainSpec] = (),
    *,
    keep_jobs: int = 1,
    registry: Registry | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> PrunePlan:
    """Find the results no kept chain needs, and the space their files take. Changes nothing.

    Parameters
    ----------
    archive : Archive
        The archive.
    keep : sequence of ChainSpec
        Chains kept besides the default chain and the newest jobs'.
    keep_jobs : int
        The chains of this many newest processing jobs are kept (0: none).
    registry : Registry, optional
        Where plugins are found.
    progress : callable, optional
        ``(done, total)`` acquisitions.

    Returns
    -------
    PrunePlan
    """
    chains = kept_chains(archive, keep, keep_jobs=keep_jobs, registry=registry)
    plan = PrunePlan(chains=[
        f"{c.source}: " + ", ".join(f"{t} ({' > '.join(p.describe() for p in steps)})"
                                    for t, steps in c.targets.items())
        if c.source.startswith("job") else c.source
        for c in chains
    ])
    with archive.session() as s:
        ids = list(s.scalars(select(Acquisition.id).where(
            select(StageResult.id).where(StageResult.acquisition_id == Acquisition.id)
            .exists()).order_by(Acquisition.id)))
        pinned = set(s.scalars(select(StageResultInput.input_id)))
    report = progress or (lambda _d, _t: None)
    removed_paths: dict[str, int] = {}
    kept_paths: set[str] = set()
    for start in range(0, len(ids), _PAGE):  # memory: one page of acquisitions at a time
        chunk = ids[start : start + _PAGE]
        with archive.session() as s:
            rows_by_acquisition = result_rows(s, chunk)
        for rows in rows_by_acquisition.values():
            by_id = {row.id: row for row in rows}
            keep_ids = {row.id for row in rows
                        if row.stage in ALWAYS_KEPT or row.id in pinned}
            for chain in chains:
                for patterns in chain.targets.values():
                    matched = match_path(rows, patterns)
                    if matched is not None:
                        keep_ids.update(row.id for row in matched.values())
            # ancestors of kept results are kept (a child names its parent)
            for rid in list(keep_ids):
                row = by_id.get(rid)
                while row is not None and row.parent_id is not None:
                    keep_ids.add(row.parent_id)
                    row = by_id.get(row.parent_id)
            depth = _depths(rows)
            plan.results += len(rows)
            for row in rows:
                if row.id in keep_ids:
                    plan.kept += 1
                    kept_paths.add(row.store_path)
                    continue
                plan.remove.append((row.id, row.store_path, depth[row.id]))
                plan.per_stage[row.stage] = plan.per_stage.get(row.stage, 0) + 1
                removed_paths[row.store_path] = 0
        report(min(start + _PAGE, len(ids)), len(ids))
    root = archive.settings.archive
    for path in removed_paths:
        if path in kept_paths:
            continue  # a file shared with a kept result stays
        try:
            plan.files[path] = (root / path).stat().st_size
        except OSError:
            plan.files[path] = 0  # already gone: verify reports the row as missing
    return plan


def _running_runs(archive: Archive) -> int:
    from rasterserver.runner import runner_gone

    with archive.session() as s:
        runners = list(s.scalars(select(PipelineRun.runner)
                                 .where(PipelineRun.status == "running")))
    # a run of another host (or recorded before runs named their process) cannot be
    # checked from here: taken as alive
    return sum(1 for runner in runners if not runner or not runner_gone(runner))


def run_prune(archive: Archive, plan: PrunePlan, *, force: bool = False) -> PruneReport:
    """Remove what ``plan`` lists: rows in one transaction, then their files.

    Parameters
    ----------
    archive : Archive
        The archive ``plan`` was made for.
    plan : PrunePlan
        From :func:`plan_prune`.
    force : bool
        Prune although pipeline runs are recorded as running (their processes are known to
        have stopped, on hosts that cannot be checked from here).

    Returns
    -------
    PruneReport

    Raises
    ------
    ConflictError
        A pipeline run is in progress (a run may be about to reuse a result removed), or a
        result to remove gained a child or a comparison since the plan (nothing removed).
    """
    report = PruneReport()
    if not plan.remove:
        return report
    running = _running_runs(archive)
    if running and not force:
        raise ConflictError(
            f"{running} pipeline run(s) in progress: prune when processing has finished "
            "(`rasterserver runs reap` marks those of stopped processes)"
        )
    from sqlalchemy.exc import IntegrityError as SQLIntegrityError

    ordered = sorted(plan.remove, key=lambda item: -item[2])
    try:
        with archive.session() as s:
            # children before parents: a foreign key refuses a parent with a child left
            for depth in sorted({d for _i, _p, d in ordered}, reverse=True):
                ids = [rid for rid, _p, d in ordered if d == depth]
                for start in range(0, len(ids), _PAGE):
                    done = s.execute(delete(StageResult).where(
                        StageResult.id.in_(ids[start : start + _PAGE]))
                        .execution_options(synchronize_session=False))
                    report.rows_removed += getattr(done, "rowcount", 0) or 0
    except SQLIntegrityError:
        # a result kept since the plan (a new child or comparison refers to it): the
        # transaction is rolled back whole, nothing was removed
        raise ConflictError("results to remove are now referred to by new results: run "
                            "prune again") from None
    root = archive.settings.archive
    paths = list(plan.files)
    for start in range(0, len(paths), _PAGE):
        chunk = paths[start : start + _PAGE]
        with archive.session() as s:
            used = set(s.scalars(select(StageResult.store_path)
                                 .where(StageResult.store_path.in_(chunk))))
        for path in chunk:
            if path in used:
                report.files_still_used += 1  # adopted by a new result meanwhile: stays
                continue
            _unlink(root, path, report)
    log.info("pruned %d result(s), %d file(s), %d bytes", report.rows_removed,
             report.files_removed, report.bytes_freed)
    return report


def _unlink(root: Path, relative: str, report: PruneReport) -> None:
    target = root / relative
    # only files of the derived area, whatever a row says
    if not target.resolve().is_relative_to((root / DERIVED_AREA).resolve()):
        log.warning("not deleting %s: outside the derived area", relative)
        return
    try:
        size = target.stat().st_size
        target.unlink()
    except FileNotFoundError:
        report.files_missing += 1
        return
    report.files_removed += 1
    report.bytes_freed += size

