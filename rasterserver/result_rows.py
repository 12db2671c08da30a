"""Writing :class:`~rasterserver.catalog.models.StageResult` rows: one way, for every caller.

A stored result is a derived file (written durably first, :mod:`rasterserver.store.derived`)
and then its row. Two processes may store the same computation at once (same acquisition,
same chain key): the second insert hits the unique constraint, and that process adopts the
row already there instead of failing. :class:`rasterserver.pipeline.Pipeline` and
:mod:`rasterserver.stored_comparison` both store results this way.
"""

from __future__ import annotations

import datetime as dt
import socket
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError as SQLIntegrityError
from sqlalchemy.orm import Session

from rasterserver import __version__
from rasterserver.catalog.models import PipelineRun, StageResult
from rasterserver.chain import Computation, Plan
from rasterserver.records import Record

__all__ = ["ProcessResult", "StepOutcome", "add_or_adopt", "commit_rows", "result_row"]


@dataclass(frozen=True)
class StepOutcome:
    """How one stage of a processed acquisition came about."""

    kind: str
    plugin: str
    result_id: int
    reused: bool
    duration_s: float
    reason: str
    store_path: str
    output_checksum: str


@dataclass
class ProcessResult:
    """The outcome of processing one acquisition.

    Attributes
    ----------
    uid : str
        The acquisition.
    run_id : int
        Its :class:`PipelineRun` row.
    steps : list of StepOutcome
        One per stage, in order.
    final : Record or None
        The last stage's record (loaded from its file when reused).
    records : dict of str to Record
        Records computed in this run (reused ones are not loaded).
    """

    uid: str
    run_id: int
    steps: list[StepOutcome]
    final: Record | None = None
    records: dict[str, Record] = field(default_factory=dict)

    @property
    def computed(self) -> int:
        """Number of stages computed in this run."""
        return sum(not s.reused for s in self.steps)

    @property
    def reused(self) -> int:
        """Number of stages whose stored result was reused."""
        return sum(s.reused for s in self.steps)

    @property
    def reason(self) -> str:
        """The last stage's reason (why it is empty, or a note)."""
        return self.steps[-1].reason if self.steps else ""


def result_row(
    *,
    record_kind: str,
    reason: str,
    acquisition_id: int,
    frame_index: int,
    stage: str,
    plugin: str,
    plugin_version: str,
    plugin_package: str,
    params: Mapping[str, Any],
    params_hash: str,
    chain_key: str,
    input_checksum: str,
    output_checksum: str,
    store_path: str,
    duration_s: float,
    run_id: int | None = None,
    parent_id: int | None = None,
    calibration_id: int | None = None,
    host: str | None = None,
) -> StageResult:
    """A new, unsaved row for a result stored at ``store_path``.

    Parameters
    ----------
    record_kind : str
        The result's record kind.
    reason : str
        Its ``reason`` (why it is empty, or a note; empty if it has none).
    host : str, optional
        Where it was computed; this host by default.
    acquisition_id, frame_index, stage, plugin, plugin_version, plugin_package, params, \
params_hash, chain_key, input_checksum, output_checksum, store_path, duration_s, run_id, \
parent_id, calibration_id
        The columns of the same names.

    Returns
    -------
    StageResult
    """
    return StageResult(
        acquisition_id=acquisition_id,
        run_id=run_id,
        parent_id=parent_id,
        calibration_id=calibration_id,
        frame_index=frame_index,
        stage=stage,
        plugin=plugin,
        plugin_version=plugin_version,
        plugin_package=plugin_package,
        params=dict(params),
        params_hash=params_hash,
        chain_key=chain_key,
        input_checksum=input_checksum,
        output_checksum=output_checksum,
        record_kind=record_kind,
        store_path=store_path,
        reason=reason,
        package_version=__version__,
        host=host or socket.gethostname(),
        duration_s=float(duration_s),
        created_at=dt.datetime.now(dt.UTC),
    )


def add_or_adopt(
    s: Session,
    row: StageResult,
    *,
    then: Callable[[StageResult], None] | None = None,
) -> tuple[StageResult, bool]:
    """Insert ``row`` in a savepoint of ``s``, or adopt the row that stores the same result.

    Parameters
    ----------
    s : sqlalchemy.orm.Session
        Inside a transaction; nothing is committed here.
    row : StageResult
        From :func:`result_row`.
    then : callable, optional
        Called with the flushed row (its id known) inside the same savepoint, to add rows
        that belong to it (a comparison's inputs); undone with it if the insert conflicts.

    Returns
    -------
    (StageResult, bool)
        The row in the catalogue, and whether it was already there (adopted).

    Raises
    ------
    sqlalchemy.exc.IntegrityError
        The insert failed for another reason than an existing row with the same key.
    """
    try:
        with s.begin_nested():
            s.add(row)
            if then is not None:
                s.flush()
                then(row)
            s.flush()
    except SQLIntegrityError:
        # another process stored the same computation meanwhile: use its row
        existing = s.scalar(
            select(StageResult).where(
                StageResult.acquisition_id == row.acquisition_id,
                StageResult.chain_key == row.chain_key,
            )
        )
        if existing is None:
            raise
        return existing, True
    return row, False


def _add(s: Session, row: StageResult) -> tuple[StageResult, bool]:
    s.add(row)
    s.flush()  # its id: the next stage's row names it as parent
    return row, False


def commit_rows(
    s: Session, plan: Plan, computation: Computation, *, adopt: bool = True
) -> ProcessResult:
    """Add the rows of ``plan``'s computed steps (files already durable) and finish its run.

    In ``s``'s transaction; a row whose result another process stored meanwhile is adopted.
    With ``adopt=False`` the rows are inserted without a savepoint each (two statements
    fewer per row): a row stored meanwhile then raises ``sqlalchemy.exc.IntegrityError``,
    and the caller, which holds a savepoint around the call, rolls back and calls again
    with ``adopt=True`` (:meth:`rasterserver.pipeline.Pipeline.commit_many`).

    Returns
    -------
    ProcessResult
        Without its final record (the caller adds it).
    """
    outcomes: list[StepOutcome] = []
    for step, cached in zip(plan.steps[: plan.first], plan.cached[: plan.first], strict=True):
        assert cached is not None
        outcomes.append(
            StepOutcome(
                step.kind,
                step.plugin,
                cached.result_id,
                True,
                0.0,
                cached.reason,
                cached.store_path,
                cached.output_checksum,
            )
        )
    parent_id = outcomes[-1].result_id if outcomes else None
    for step, key in zip(plan.to_compute, plan.keys[plan.first :], strict=True):
        stored, in_sum = computation.stored[step.kind]
        row, reused = (add_or_adopt if adopt else _add)(
            s,
            result_row(
                record_kind=stored.record_kind,
                reason=stored.reason,
                acquisition_id=plan.acquisition_id,
                run_id=plan.run_id,
                parent_id=parent_id,
                calibration_id=(
                    plan.calibration_id
                    if {"calibration", "raster"} & set(step.requires)
                    else None
                ),
                frame_index=plan.frame_index,
                stage=step.kind,
                plugin=step.plugin,
                plugin_version=step.version,
                plugin_package=step.package,
                params=step.params,
                params_hash=step.params_hash,
                chain_key=key,
                input_checksum=in_sum,
                output_checksum=stored.output_checksum,
                store_path=stored.path,
                host=computation.host,
                duration_s=computation.durations.get(step.kind, 0.0),
            ),
        )
        parent_id = row.id
        outcomes.append(
            StepOutcome(
                step.kind,
                step.plugin,
                row.id,
                reused,
                row.duration_s,
                row.reason,
                row.store_path,
                row.output_checksum,
            )
        )
    s.execute(
        update(PipelineRun)
        .where(PipelineRun.id == plan.run_id)
        .values(
            status="done",
            finished_at=dt.datetime.now(dt.UTC),
            computed=sum(not o.reused for o in outcomes),
            reused=sum(o.reused for o in outcomes),
        )
    )
    return ProcessResult(plan.uid, plan.run_id, outcomes, None, dict(computation.records))
