"""Planning a page of acquisitions at once (Pipeline.plan_many): same plans as one by one,
errors per acquisition, stored results found; committing with a row stored meanwhile."""

from __future__ import annotations

import geometry_truth as gt
import numpy as np
from sqlalchemy import select

from rasterserver.catalog.models import PipelineRun
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
