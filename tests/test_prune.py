"""``rasterserver.prune`` and ``rasterserver.archive_stats`` on SQLite and PostgreSQL: what is
kept (default chain, --keep chains, newest jobs, what a comparison refers to), rows before
files, a crash between the two, and refusal while a run is in progress."""

from __future__ import annotations

import datetime as dt

import geometry_truth as gt
import numpy as np
import pytest
from sqlalchemy import func, select

from rasterserver import prune as prune_module
from rasterserver.archive import Archive
from rasterserver.archive_stats import archive_stats
from rasterserver.catalog.models import PipelineRun, StageResult, StageResultInput
from rasterserver.chain_spec import parse_chain
from rasterserver.config import Settings
from rasterserver.errors import ConflictError
from rasterserver.pipeline import Pipeline
from rasterserver.processing_jobs import Selection, create_job
from rasterserver.prune import plan_prune, run_prune
from rasterserver.runner import current_runner

OLD = {"peaks": {"bias_fraction": 0.3}}
STAGES = 8  # peaks .. mesh, and the analysis


def processed_twice(settings: Settings) -> tuple[Archive, dict[str, str]]:
    """A back and a black frame processed with OLD, then with the default chain."""
    image = gt.rendering("back").image
    archive, uids = gt.archive_with_frames(settings, {"back": image,
                                                      "black": np.zeros_like(image)})
    pipeline = Pipeline(archive)
    for params in (OLD, None):
        for uid in uids.values():
            for until in ("mesh", "analysis"):
                pipeline.process(uid, until=until, params=params)
    return archive, uids


def rows(archive: Archive) -> int:
    with archive.session() as s:
        return int(s.scalar(select(func.count(StageResult.id))))


def refer(archive: Archive, uid: str, stage: str, params_hash: str) -> int:
    """Store a comparison-like result referring to ``uid``'s result of ``stage`` made with
    ``params_hash`` upstream (through stage_result_input), as stored comparisons do."""
    acquisition = archive.acquisition(uid)
    with archive.session() as s:
        candidates = list(s.scalars(select(StageResult).where(
            StageResult.acquisition_id == acquisition.id, StageResult.stage == stage)))
        by_id = {r.id: r for r in s.scalars(select(StageResult).where(
            StageResult.acquisition_id == acquisition.id))}

        def first_hash(r: StageResult) -> str:
            while r.parent_id is not None:
                r = by_id[r.parent_id]
            return r.params_hash

        target = next(r for r in candidates if first_hash(r) == params_hash)
        row = StageResult(
            acquisition_id=acquisition.id, frame_index=0, stage="comparison",
            plugin="comparison.landmark-icp", plugin_version="1", params={},
            params_hash="0" * 64, chain_key="c" * 64, input_checksum="0" * 64,
            # its file: the analysis's (a real comparison has its own; verify reads this one)
            output_checksum=target.output_checksum, record_kind=target.record_kind,
            store_path=target.store_path,
            created_at=dt.datetime.now(dt.UTC))
        s.add(row)
        s.flush()
        s.add(StageResultInput(result_id=row.id, position=0, role="a.analysis",
                               input_id=target.id, acquisition_id=acquisition.id))
        return target.id


def test_prune_keeps_what_is_needed_and_frees_the_rest(settings: Settings, monkeypatch) -> None:
    archive, uids = processed_twice(settings)
    with archive:
        assert rows(archive) == 2 * 2 * STAGES
        old_hash = next(r.params_hash for r in Pipeline(archive).results(uids["back"])
                        if r.stage == "peaks" and r.params == {**r.params, "bias_fraction": 0.3})

        everything = plan_prune(archive, [parse_chain("peaks.bias_fraction=0.3")])
        assert everything.remove == [] and everything.kept == 2 * 2 * STAGES
        plan = plan_prune(archive)
        # the old chain's results of both acquisitions go (the black frame's too: its empty
        # results are keyed by the chain as well)
        assert len(plan.remove) == 2 * STAGES and plan.kept == 2 * STAGES
        assert plan.bytes > 0 and plan.per_stage["peaks"] == 2

        protected = refer(archive, uids["back"], "analysis", old_hash)
        plan = plan_prune(archive)
        removed = {rid for rid, _path, _depth in plan.remove}
        assert protected not in removed
        # the analysis and its ancestors stay (peaks .. surface); the old mesh goes
        assert len(plan.remove) == 2 * STAGES - 7
        stats = archive_stats(archive, prune=True)
        assert stats.prune["remove"] == len(plan.remove) and stats.counts["acquisitions"] == 2
        assert stats.files["raw frames"]["files"] == 2 and stats.chains[0]["acquisitions"] == 2

        # a crash after the rows' commit, before the files: orphaned files, never a
        # row without its file
        calls = []

        def killed(*args):
            calls.append(args)
            raise KeyboardInterrupt

        monkeypatch.setattr(prune_module, "_unlink", killed)
        with pytest.raises(KeyboardInterrupt):
            run_prune(archive, plan)
        assert rows(archive) == 2 * 2 * STAGES + 1 - len(plan.remove)
        kinds = {p.kind for p in Pipeline(archive).verify().problems}
        assert kinds == {"orphaned"}
        monkeypatch.undo()

        # nothing left in the catalogue to remove; the old chain computed again adopts its
        # orphaned files (their names follow from the chain keys)
        assert plan_prune(archive).remove == []
        Pipeline(archive).process(uids["black"], until="mesh", params=OLD)
        left = {p.kind for p in Pipeline(archive).verify().problems}
        assert left <= {"orphaned"}


def test_prune_removes_files_and_keeps_the_newest_jobs_chain(settings: Settings) -> None:
    archive, uids = processed_twice(settings)
    with archive:
        create_job(archive, Selection(all=True), params=OLD, targets=["mesh"])
        plan = plan_prune(archive)  # the newest job ran OLD up to the mesh: kept
        assert len(plan.remove) == 2  # only OLD's analyses
        plan = plan_prune(archive, keep_jobs=0)
        before = sum(f.stat().st_size for f in (settings.archive / "derived").rglob("*.h5"))
        done = run_prune(archive, plan)
        after = sum(f.stat().st_size for f in (settings.archive / "derived").rglob("*.h5"))
        assert done.rows_removed == 2 * STAGES and done.files_removed == len(plan.files)
        assert done.bytes_freed == plan.bytes == before - after
        assert Pipeline(archive).verify().problems == []
        assert archive.verify().problems == []  # raw frames untouched
        again = Pipeline(archive).process(uids["back"], until="mesh")
        assert again.computed == 0  # the default chain is whole

        with archive.session() as s:
            s.add(PipelineRun(acquisition_id=archive.acquisition(uids["back"]).id, chain=[],
                              status="running", runner=current_runner()))
        Pipeline(archive).process(uids["back"], until="mesh", params=OLD)
        with pytest.raises(ConflictError, match="in progress"):
            run_prune(archive, plan_prune(archive, keep_jobs=0))
        assert run_prune(archive, plan_prune(archive, keep_jobs=0), force=True).rows_removed


def test_prune_keeps_the_files_a_kept_result_inherits_from(settings: Settings) -> None:
    # two chains sharing peaks .. order: the default one's numbering inherits the peaks'
    # fields from the shared results (derived format 3); pruning the other chain must leave
    # them, and everything kept readable
    image = gt.rendering("back").image
    archive, uids = gt.archive_with_frames(settings, {"back": image})
    uid = uids["back"]
    with archive:
        pipeline = Pipeline(archive)
        pipeline.process(uid, until="mesh", params={"numbers": {"min_run": 0}})
        pipeline.process(uid, until="mesh")
        stages = [r.stage for r in pipeline.results(uid)]
        assert [stages.count(k) for k in ("peaks", "lines", "order", "numbers")] == [1, 1, 1, 2]
        plan = plan_prune(archive)
        assert len(plan.remove) == 4  # the other chain's numbers, points, surface, mesh
        run_prune(archive, plan)
        assert pipeline.verify().problems == []
        row, _ = pipeline.result(uid, "numbers")
        base = pipeline.derived.metadata(row.store_path)["base"]
        assert base in {r.store_path for r in pipeline.results(uid) if r.stage == "order"}
        assert (settings.archive / base).is_file()
        assert pipeline.process(uid, until="mesh").computed == 0
