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
from typing import Any, cast

from sqlalchemy import Table, bindparam, insert, select, update
from sqlalchemy.exc import IntegrityError as SQLIntegrityError
from sqlalchemy.orm import Session

from rasterserver import __version__
from rasterserver.catalog.models import PipelineRun, StageResult
from rasterserver.chain import Computation, Plan
from rasterserver.records import Record

__all__ = [
    "ProcessResult",
    "StepOutcome",
    "add_or_adopt",
    "commit_rows",
    "commit_rows_many",
    "result_fields",
    "result_row",
]

# the tables as Core sees them, for the bulk statements (the ORM declares them FromClauses)
_RESULTS = cast(Table, StageResult.__table__)
_RUNS = cast(Table, PipelineRun.__table__)


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


def result_row(**fields: Any) -> StageResult:
    """A new, unsaved row for a result: :func:`result_fields` (same parameters) as a row."""
    return StageResult(**result_fields(**fields))


def result_fields(
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
) -> dict[str, Any]:
    """The column values of a new result row, for a result stored at ``store_path``.

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
    dict
        Column name to value (a bulk insert's parameters).
    """
    return dict(
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


def _reused_outcomes(plan: Plan) -> list[StepOutcome]:
    # the plan's leading steps, stored already
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
    return outcomes


def _computed_fields(
    plan: Plan, computation: Computation, position: int, parent_id: int | None
) -> dict[str, Any]:
    # the columns of the row of the plan's computed step at ``position`` (of to_compute)
    step = plan.to_compute[position]
    stored, in_sum = computation.stored[step.kind]
    return result_fields(
        record_kind=stored.record_kind,
        reason=stored.reason,
        acquisition_id=plan.acquisition_id,
        run_id=plan.run_id,
        parent_id=parent_id,
        calibration_id=(
            plan.calibration_id if {"calibration", "raster"} & set(step.requires) else None
        ),
        frame_index=plan.frame_index,
        stage=step.kind,
        plugin=step.plugin,
        plugin_version=step.version,
        plugin_package=step.package,
        params=step.params,
        params_hash=step.params_hash,
        chain_key=plan.keys[plan.first + position],
        input_checksum=in_sum,
        output_checksum=stored.output_checksum,
        store_path=stored.path,
        host=computation.host,
        duration_s=computation.durations.get(step.kind, 0.0),
    )


def _outcome(fields: Mapping[str, Any], row_id: int, reused: bool) -> StepOutcome:
    return StepOutcome(
        fields["stage"],
        fields["plugin"],
        row_id,
        reused,
        fields["duration_s"],
        fields["reason"],
        fields["store_path"],
        fields["output_checksum"],
    )


def _result(plan: Plan, computation: Computation, outcomes: list[StepOutcome]) -> ProcessResult:
    return ProcessResult(plan.uid, plan.run_id, outcomes, None, dict(computation.records))


def _finish_runs(s: Session, results: list[ProcessResult]) -> None:
    # every run done, with its counts: one statement for all
    if not results:
        return
    table = _RUNS
    s.connection().execute(
        update(table)
        .where(table.c.id == bindparam("run_id"))
        .values(
            status="done",
            finished_at=bindparam("finished_at"),
            computed=bindparam("done_computed"),
            reused=bindparam("done_reused"),
        ),
        [
            {
                "run_id": r.run_id,
                "finished_at": dt.datetime.now(dt.UTC),
                "done_computed": r.computed,
                "done_reused": r.reused,
            }
            for r in results
        ],
    )


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
    outcomes = _reused_outcomes(plan)
    parent_id = outcomes[-1].result_id if outcomes else None
    for position in range(len(plan.to_compute)):
        fields = _computed_fields(plan, computation, position, parent_id)
        row, reused = (add_or_adopt if adopt else _add)(s, StageResult(**fields))
        parent_id = row.id
        outcomes.append(
            StepOutcome(
                row.stage,
                row.plugin,
                row.id,
                reused,
                row.duration_s,
                row.reason,
                row.store_path,
                row.output_checksum,
            )
        )
    result = _result(plan, computation, outcomes)
    _finish_runs(s, [result])
    return result


def commit_rows_many(
    s: Session, done: list[tuple[Plan, Computation]]
) -> list[ProcessResult]:
    """:func:`commit_rows` (``adopt=False``) for several acquisitions, in a few statements.

    The rows of each chain position go in one multi-row ``INSERT ... RETURNING`` for all
    acquisitions (their ids, in order, are the next position's parents), and the runs are
    finished in one ``UPDATE``: seven statements for a batch of mesh chains instead of seven
    flushes per acquisition. A row another process stored meanwhile raises
    ``sqlalchemy.exc.IntegrityError`` and nothing of the batch is kept (the caller holds a
    savepoint and goes acquisition by acquisition instead).

    Returns
    -------
    list of ProcessResult
        Without their final records (the caller adds them), in the order of ``done``.
    """
    table = _RESULTS
    insert_rows = insert(table).returning(table.c.id, sort_by_parameter_order=True)
    outcomes = [_reused_outcomes(plan) for plan, _c in done]
    parents: list[int | None] = [o[-1].result_id if o else None for o in outcomes]
    depth = max((len(plan.to_compute) for plan, _c in done), default=0)
    for position in range(depth):
        which = [i for i, (plan, _c) in enumerate(done) if position < len(plan.to_compute)]
        rows = [_computed_fields(*done[i], position, parents[i]) for i in which]
        ids = list(s.connection().execute(insert_rows, rows).scalars())
        for i, fields, row_id in zip(which, rows, ids, strict=True):
            parents[i] = row_id
            outcomes[i].append(_outcome(fields, row_id, False))
    results = [
        _result(plan, computation, steps)
        for (plan, computation), steps in zip(done, outcomes, strict=True)
    ]
    _finish_runs(s, results)
    return results
