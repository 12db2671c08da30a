"""The work of a batch of acquisitions on a worker: computed and written in order, each
failure reported in its own place."""

from __future__ import annotations

import geometry_truth as gt
import numpy as np

from rasterserver.chain import Computation
from rasterserver.config import Settings
from rasterserver.pipeline import Pipeline, Plan
from rasterserver.store.derived import DerivedStore
from rasterserver.worker import work_batch


def test_a_failed_write_is_reported_for_its_acquisition_alone(settings: Settings) -> None:
    image = gt.rendering("back").image
    archive, uids = gt.archive_with_frames(
        settings, {"a": image, "b": image[:, ::-1].copy(), "c": np.roll(image, 3, axis=0)}
    )
    with archive:
        pipeline = Pipeline(archive)
        order = [uids["a"], uids["b"], uids["c"]]
        plans = [p for p in pipeline.plan_many(order, until="mesh") if isinstance(p, Plan)]
        assert len(plans) == 3
        # b's shard folder is taken by a file: its results cannot be written
        derived = DerivedStore(settings.archive)
        first = plans[1].to_compute[0].kind
        blocked = derived.path_for(plans[1].uid, first, plans[1].keys[plans[1].first]).parent
        blocked.parent.mkdir(parents=True, exist_ok=True)
        blocked.write_bytes(b"not a folder")
        out = work_batch(plans, settings.archive, keep="none")
        assert isinstance(out[0], Computation) and isinstance(out[2], Computation)
        assert isinstance(out[1], OSError)
        for done in (out[0], out[2]):
            assert len(done.stored) == 7
            assert all(stored.path for stored, _checksum in done.stored.values())
        # the batch's files were made durable together and published: none left unnamed
        kinds = [entry.kind for entry in derived.scan()]
        assert kinds.count("final") == 14 and "temp" not in kinds
        results = pipeline.commit_many([(plans[0], out[0]), (plans[2], out[2])], final=False)
        assert all(not isinstance(r, BaseException) and r.computed == 7 for r in results)


def test_an_empty_batch_and_a_plan_with_nothing_to_compute(settings: Settings) -> None:
    assert work_batch([], settings.archive) == []
    image = gt.rendering("back").image
    archive, uids = gt.archive_with_frames(settings, {"a": image})
    with archive:
        pipeline = Pipeline(archive)
        (plan,) = pipeline.plan_many([uids["a"]], until="mesh")
        assert isinstance(plan, Plan)
        (done,) = work_batch([plan], settings.archive, keep="none")
        assert isinstance(done, Computation)
        pipeline.commit_many([(plan, done)], final=False)
        (again,) = pipeline.plan_many([uids["a"]], until="mesh")
        assert isinstance(again, Plan) and again.first == len(again.steps)
        (nothing,) = work_batch([again], settings.archive)
        assert isinstance(nothing, Computation) and nothing.stored == {}
