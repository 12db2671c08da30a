"""Planning a page of acquisitions at once (Pipeline.plan_many): same plans as one by one,
errors per acquisition, stored results found; committing with a row stored meanwhile."""

from __future__ import annotations

import geometry_truth as gt
import numpy as np
from sqlalchemy import select

from rasterserver.catalog.models import PipelineRun, StageResult
from rasterserver.config import Settings
from rasterserver.errors import NotFoundError
from rasterserver.pipeline import Pipeline


def test_plan_many_matches_plan_and_reports_errors_per_acquisition(settings: Settings) -> None:
    image = gt.rendering("back").image
    archive, uids = gt.archive_with_frames(
        settings, {"a": image, "b": image, "black": np.zeros_like(image)}
    )
    with archive:
        pipeline = Pipeline(archive)
        done = pipeline.process(uids["a"], until="points")
        order = [uids["a"], "f" * 32, uids["b"], uids["black"]]
        plans = pipeline.plan_many(order, until="mesh")
        assert isinstance(plans[1], NotFoundError)
        first, _, second, black = plans
        assert not isinstance(first, BaseException) and not isinstance(second, BaseException)
        assert not isinstance(black, BaseException)
        alone = pipeline.plan(uids["b"], until="mesh", load_input=False)
        assert second.keys == alone.keys and second.first == 0 and second.cached == alone.cached
        # the stored prefix of "a" is found: computing starts after points
        assert first.first == len(done.steps)
        assert [c.store_path for c in first.cached[: first.first]] == [
            s.store_path for s in done.steps
        ]
        assert first.input_record is None and second.input_record is None
        # every plan opened a running run of its own
        with archive.session() as s:
            running = set(s.scalars(select(PipelineRun.id).where(PipelineRun.status == "running")))
        assert {first.run_id, second.run_id, black.run_id, alone.run_id} <= running
        # the plans compute and commit like plan()'s, a row stored meanwhile being adopted
        results = pipeline.commit_many([(p, pipeline.compute(p)) for p in (first, second)])
        assert all(not isinstance(r, BaseException) for r in results)
        adopted = pipeline.commit(alone, pipeline.compute(alone))
        assert all(step.reused for step in adopted.steps)
        assert adopted.steps[-1].result_id == results[1].steps[-1].result_id


def test_a_batch_with_a_row_stored_meanwhile_commits_the_others_and_adopts_it(
    settings: Settings,
) -> None:
    # the batch's rows go in one statement per chain position; one acquisition's rows stored
    # by another process meanwhile undo that statement, and the batch goes one by one:
    # that acquisition adopts the stored rows, the others are inserted, parents chained
    image = gt.rendering("back").image
    archive, uids = gt.archive_with_frames(
        settings, {"a": image, "b": image, "black": np.zeros_like(image)}
    )
    with archive:
        pipeline = Pipeline(archive)
        plans = pipeline.plan_many([uids["a"], uids["b"], uids["black"]], until="mesh")
        assert not any(isinstance(p, BaseException) for p in plans)
        computed = [(p, pipeline.compute(p)) for p in plans]  # type: ignore[arg-type]
        other = pipeline.plan(uids["b"], until="mesh", load_input=False)
        stored = pipeline.commit(other, pipeline.compute(other))  # "another process"
        results = pipeline.commit_many(computed)
        assert all(not isinstance(r, BaseException) for r in results)
        a, b, black = results
        assert all(step.reused for step in b.steps)  # adopted
        assert [s.result_id for s in b.steps] == [s.result_id for s in stored.steps]
        assert not any(step.reused for step in a.steps + black.steps)
        with archive.session() as s:
            rows = {r.id: r for r in s.scalars(select(StageResult))}
            runs = {r.id: r.status for r in s.scalars(select(PipelineRun))}
        for result in (a, black):
            ids = [step.result_id for step in result.steps]
            assert [rows[i].parent_id for i in ids] == [None, *ids[:-1]]
            assert runs[result.run_id] == "done"
        assert len(rows) == 21


def test_a_batch_commits_its_rows_chained_in_a_few_statements(settings: Settings) -> None:
    image = gt.rendering("back").image
    archive, uids = gt.archive_with_frames(settings, {"a": image, "b": image})
    with archive:
        pipeline = Pipeline(archive)
        plans = pipeline.plan_many([uids["a"], uids["b"]], until="mesh")
        computed = [(p, pipeline.compute(p)) for p in plans]  # type: ignore[arg-type]
        statements: list[str] = []
        from sqlalchemy import event

        def count(conn, cursor, statement, *args) -> None:
            if statement.lstrip().upper().startswith("INSERT INTO STAGE_RESULT"):
                statements.append(statement)

        event.listen(archive.engine, "before_cursor_execute", count)
        try:
            results = pipeline.commit_many(computed)
        finally:
            event.remove(archive.engine, "before_cursor_execute", count)
        assert all(not isinstance(r, BaseException) for r in results)
        # PostgreSQL: one multi-row INSERT ... RETURNING per chain position for both; SQLite:
        # SQLAlchemy sends ordered RETURNING rows one at a time, still without ORM flushes
        on_postgres = settings.database_url.startswith("postgresql")
        assert len(statements) <= (7 if on_postgres else 14)
        with archive.session() as s:
            rows = {r.id: (r.parent_id, r.acquisition_id) for r in s.scalars(select(StageResult))}
        for plan, result in zip(plans, results, strict=True):
            ids = [step.result_id for step in result.steps]  # type: ignore[union-attr]
            assert [rows[i][0] for i in ids] == [None, *ids[:-1]]
            assert {rows[i][1] for i in ids} == {plan.acquisition_id}  # type: ignore[union-attr]


def test_a_job_gets_no_records_back_and_reads_no_final_file(settings: Settings) -> None:
    # work_batch(keep="none") sends only what was stored back (a worker would otherwise send
    # each acquisition's mesh over the network), and commit_many(final=False) reads no file
    from rasterserver.chain import Computation
    from rasterserver.pipeline import Plan
    from rasterserver.worker import work_batch

    image = gt.rendering("back").image
    archive, uids = gt.archive_with_frames(settings, {"a": image, "black": np.zeros_like(image)})
    with archive:
        pipeline = Pipeline(archive)
        plans = [
            p
            for p in pipeline.plan_many([uids["a"], uids["black"]], until="mesh", load_input=False)
            if isinstance(p, Plan)
        ]
        computations = [
            c
            for c in work_batch(plans, settings.archive, keep="none")
            if isinstance(c, Computation)
        ]
        assert len(plans) == len(computations) == 2
        assert all(c.records == {} and len(c.stored) == 7 for c in computations)
        results = pipeline.commit_many(list(zip(plans, computations, strict=True)), final=False)
        done = [r for r in results if not isinstance(r, BaseException)]
        assert [(r.computed, r.final) for r in done] == [(7, None), (7, None)]
        # the default still loads the final record (what `process` shows), from its file
        again = pipeline.plan(uids["a"], until="mesh", load_input=False)
        (computed,) = work_batch([again], settings.archive)
        assert isinstance(computed, Computation)
        (shown,) = pipeline.commit_many([(again, computed)])
        assert not isinstance(shown, BaseException) and shown.final is not None
        assert shown.final.kind == "mesh" and shown.reused == 7
