"""The pipeline: in-memory chains, and archived processing with storage, provenance and reuse.

Archive tests run on SQLite and PostgreSQL (the ``settings`` fixture).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import geometry_truth as gt
import numpy as np
import pytest
from sqlalchemy import func, select

from rasterserver.catalog.models import PipelineRun, StageResult
from rasterserver.config import Settings
from rasterserver.errors import InputError, NotFoundError
from rasterserver.optics import default_station
from rasterserver.pipeline import Pipeline, parse_stage_options, resolve_chain, run_chain
from rasterserver.records_surface import MeshRecord, Points, Surface
from rasterserver.stage import BUILTIN_STAGE_KINDS, StageContext

CHAIN = list(BUILTIN_STAGE_KINDS)


def _context() -> StageContext:
    station = gt.station()
    return StageContext(calibration=station, raster=station.raster_definition)


# --- in memory ---------------------------------------------------------------------------------


def test_run_chain_from_a_rendered_back_meets_the_accuracy_targets() -> None:
    rendering = gt.rendering("back")
    durations: dict[str, float] = {}
    results = run_chain(rendering.image, context=_context(), durations=durations)
    assert list(results) == CHAIN and list(durations) == CHAIN
    points, surface, mesh = results["points"], results["surface"], results["mesh"]
    assert isinstance(points, Points) and isinstance(surface, Surface)
    assert isinstance(mesh, MeshRecord)
    assert 15_000 < len(points) < 30_000  # the seed: ≈ 25,000 peaks ...
    assert len(surface.samples) == pytest.approx(len(points) / 3, rel=0.05)  # ... ≈ 8,000
    scene = gt.scene("back")
    assert gt.rms(gt.distance_to_scene(scene, points.xyz)) <= 0.5
    assert gt.rms(gt.distance_to_scene(scene, surface.samples)) <= 0.2
    assert gt.rms(gt.distance_to_scene(scene, surface.grid_points())) <= 0.2
    assert len(mesh.triangles) > 30_000


def test_run_chain_can_start_from_an_intermediate_record() -> None:
    pytest.importorskip("rasterserver.records_lines")
    rendering = gt.rendering("sphere")
    lines = gt.numbered_lines(rendering.line_rows, rendering.image.shape)
    results = run_chain(lines, context=_context(), until="surface")
    assert list(results) == ["points", "surface"]
    with pytest.raises(InputError, match="come before"):
        run_chain(lines, context=_context(), chain={"peaks": "peaks.first-moment"})


def test_run_chain_refuses_a_frame_of_another_size() -> None:
    frame = np.zeros((480, 640), np.uint8)
    with pytest.raises(InputError, match=r"480x640.*604x576"):
        run_chain(frame, context=_context())


@pytest.mark.parametrize(
    ("name", "image"),
    [
        ("all-black", np.zeros((604, 576), np.uint8)),
        ("saturated", np.full((604, 576), 255, np.uint8)),
        ("raster-free", np.random.default_rng(0).integers(0, 60, (604, 576)).astype(np.uint8)),
    ],
)
def test_bad_frames_give_empty_results_with_reasons(name: str, image: np.ndarray) -> None:
    results = run_chain(image, context=_context())
    assert len(results["points"]) == 0 and results["points"].reason
    assert results["surface"].z.size == 0 and results["surface"].reason
    assert len(results["mesh"].triangles) == 0 and results["mesh"].reason


def test_a_flat_wall_is_reconstructed_as_a_plane() -> None:
    results = run_chain(gt.rendering("plane").image, context=_context())
    scene = gt.scene("plane")
    assert len(results["points"]) > 20_000
    assert gt.rms(gt.distance_to_scene(scene, results["points"].xyz)) < 0.2
    assert gt.rms(gt.distance_to_scene(scene, results["surface"].grid_points())) < 0.1


def test_chain_resolution_and_options() -> None:
    steps = resolve_chain()
    assert [s.kind for s in steps] == CHAIN
    assert steps[4].plugin == "points.ray-plane" and steps[4].requires == ("calibration", "raster")
    assert parse_stage_options(["surface=surface.linear-grid"]) == {
        "surface": "surface.linear-grid"
    }
    with pytest.raises(InputError, match="KIND=PLUGIN"):
        parse_stage_options(["surface"])
    with pytest.raises(InputError, match="unknown stage kind"):
        resolve_chain({"smoothing": "surface.linear-grid"})
    with pytest.raises(InputError, match="implements stage 'surface'"):
        resolve_chain({"mesh": "surface.linear-grid"})
    with pytest.raises(NotFoundError, match="no stage plugin named"):
        resolve_chain({"mesh": "mesh.poisson"})
    with pytest.raises(InputError, match="unknown parameter"):
        resolve_chain(params={"surface": {"spacng": 2.0}})
    with pytest.raises(InputError, match="unknown stage"):
        resolve_chain(until="no-such-kind")


def test_run_chain_needs_the_calibration() -> None:
    image = gt.rendering("plane").image
    with pytest.raises(InputError, match="needs raster"):
        run_chain(image)
    raster_only = StageContext(raster=gt.station().raster_definition)
    with pytest.raises(InputError, match="needs calibration"):
        run_chain(image, context=raster_only)


# --- archived processing -------------------------------------------------------------------------


@pytest.fixture
def archived(settings: Settings):
    archive, uids = gt.archive_with_frames(settings, {"back": gt.rendering("back").image})
    yield archive, uids["back"]
    archive.close()


def _count(archive, model, **where) -> int:
    with archive.session() as s:
        query = select(func.count()).select_from(model)
        for name, value in where.items():
            query = query.where(getattr(model, name) == value)
        return int(s.scalar(query))


def test_process_stores_every_stage_with_provenance(archived) -> None:
    archive, uid = archived
    raw = archive.raw.path_for(uid)
    raw_bytes, raw_mtime = raw.read_bytes(), os.stat(raw).st_mtime_ns
    pipeline = Pipeline(archive)
    result = pipeline.process(uid)
    assert [s.kind for s in result.steps] == CHAIN
    assert result.computed == 7 and result.reused == 0
    assert isinstance(result.final, MeshRecord) and len(result.final.triangles) > 30_000
    rows = pipeline.results(uid)
    assert [r.stage for r in rows] == CHAIN
    runs = pipeline.runs(uid)
    assert len(runs) == 1 and runs[0].status == "done" and runs[0].computed == 7
    assert runs[0].finished_at is not None and runs[0].error == ""
    assert [c["stage"] for c in runs[0].chain] == CHAIN
    calibration = archive.calibration(gt.STATION_NAME)
    assert runs[0].calibration_id == calibration.id
    previous = None
    for row in rows:
        assert row.run_id == runs[0].id
        assert row.parent_id == (previous.id if previous else None)
        assert len(row.params_hash) == len(row.chain_key) == 64
        # the version of the plugin that made it (each plugin's own, bumped as it changes)
        assert row.params and row.plugin_version == pipeline.registry.get(row.plugin).version
        assert row.package_version
        assert row.plugin_package.startswith("rasterserver ")
        assert row.host and row.duration_s > 0 and row.created_at is not None
        assert row.store_path.startswith("derived/")
        assert (archive.settings.archive / row.store_path).is_file()
        if previous is not None:
            assert row.input_checksum == previous.output_checksum  # the chain is linked
        uses_station = row.stage in ("numbers", "points")
        assert row.calibration_id == (calibration.id if uses_station else None)
        previous = row
    # the first stage's input is the raw frame itself
    frame = archive.read_frame(uid, 0)
    from rasterserver.records import Image

    assert rows[0].input_checksum == Image(frame).content_hash()
    # derived data never goes into the raw file
    assert raw.read_bytes() == raw_bytes and os.stat(raw).st_mtime_ns == raw_mtime
    points_row, points = pipeline.result(uid, "points")
    assert isinstance(points, Points) and points.content_hash() == points_row.output_checksum
    assert points == result.records["points"]
    # the line stages store only what they add to the peaks: the rest they inherit from
    # their parent's file (format version 3)
    for row, parent in zip(rows[1:4], rows[:3], strict=True):
        meta = pipeline.derived.metadata(row.store_path)
        assert meta["base"] == parent.store_path
        assert meta["base_checksum"] == parent.output_checksum
        assert {"col", "row", "area"} <= set(json.loads(meta["inherited"]))
        assert pipeline.result(uid, row.stage)[1] == result.records[row.stage]
    sizes = [(archive.settings.archive / r.store_path).stat().st_size for r in rows]
    assert max(sizes[1:4]) < sizes[0] / 2


def test_second_run_reuses_everything(archived) -> None:
    archive, uid = archived
    pipeline = Pipeline(archive)
    first = pipeline.process(uid)
    before = {r.id: r.created_at for r in pipeline.results(uid)}
    second = pipeline.process(uid)
    assert second.computed == 0 and second.reused == 7
    assert [s.result_id for s in second.steps] == [s.result_id for s in first.steps]
    assert {r.id: r.created_at for r in pipeline.results(uid)} == before
    runs = pipeline.runs(uid)
    assert [(r.status, r.computed, r.reused) for r in runs] == [("done", 7, 0), ("done", 0, 7)]
    assert second.final == first.final  # loaded from its file, checksum verified


def test_other_parameters_and_calibrations_add_results_beside_the_old(archived) -> None:
    archive, uid = archived
    pipeline = Pipeline(archive)
    pipeline.process(uid)
    finer = pipeline.process(uid, params={"surface": {"spacing": 2.0}})
    assert [s.reused for s in finer.steps] == [True] * 5 + [False, False]
    assert isinstance(finer.final, MeshRecord)
    # a recalibration (camera 0.5 mm further away) recomputes from the reconstruction on
    station = gt.station()
    camera = dataclasses.replace(station.camera, t=station.camera.t + np.array([0, 0, 0.5]))
    moved = dataclasses.replace(station, camera=camera)
    archive.add_calibration(gt.STATION_NAME, moved.to_dict(), raster="default")
    recal = pipeline.process(uid, calibration=(gt.STATION_NAME, 2))
    # the raster is the same, so numbering is reused; geometry is recomputed
    assert {s.kind: s.reused for s in recal.steps} == {
        k: k in ("peaks", "lines", "order", "numbers") for k in CHAIN
    }
    assert _count(archive, StageResult, stage="points") == 2
    assert _count(archive, StageResult, stage="surface") == 3
    newest_row, newest = pipeline.result(uid, "points")
    assert newest_row.calibration_id == archive.calibration(gt.STATION_NAME, 2).id
    first_points = pipeline.results(uid)[4]
    assert first_points.stage == "points" and first_points.id != newest_row.id
    old = archive_record(pipeline, first_points)
    assert len(old) == len(newest) and not np.allclose(old.z, newest.z, atol=0.05)


def archive_record(pipeline: Pipeline, row: StageResult):
    return pipeline.derived.read(row.store_path, expected_checksum=row.output_checksum)


def test_calibration_of_another_station_is_refused_and_the_run_failed(archived) -> None:
    archive, uid = archived
    archive.add_station("clinic-2")
    archive.add_calibration("clinic-2", gt.station().to_dict())
    pipeline = Pipeline(archive)
    with pytest.raises(InputError, match=r"station 'clinic-2'.*station 'clinic-1'"):
        pipeline.process(uid, calibration=("clinic-2", None))
    (run,) = pipeline.runs(uid)
    assert run.status == "failed" and "clinic-2" in run.error and run.finished_at is not None
    assert pipeline.results(uid) == []


def test_missing_calibration_is_a_clear_error(settings: Settings) -> None:
    archive, uids = gt.archive_with_frames(
        settings, {"back": gt.rendering("back").image}, calibrate=False
    )
    with archive:
        with pytest.raises(NotFoundError, match=r"no calibration.*--calibration"):
            Pipeline(archive).process(uids["back"])
        with pytest.raises(NotFoundError, match="has no calibration"):
            Pipeline(archive).process(uids["back"], calibration=(gt.STATION_NAME, None))
        with pytest.raises(NotFoundError, match="unknown acquisition"):
            Pipeline(archive).process("f" * 32)


def test_frame_of_another_size_than_the_camera_is_refused(settings: Settings) -> None:
    small = np.zeros((302, 288), np.uint8)
    # ingest refuses it once a calibration applies, so it is stored before there is one
    archive, uids = gt.archive_with_frames(settings, {"small": small}, calibrate=False)
    with archive:
        archive.add_calibration(gt.STATION_NAME, gt.station().to_dict())
        pipeline = Pipeline(archive)
        with pytest.raises(InputError, match=r"302x288.*604x576"):
            pipeline.process(uids["small"], calibration=(gt.STATION_NAME, 1))
        assert pipeline.runs(uids["small"])[0].status == "failed"


def test_calibration_for_another_camera_size_is_refused(settings: Settings) -> None:
    archive, uids = gt.archive_with_frames(settings, {"back": gt.rendering("back").image})
    with archive:
        archive.add_calibration(gt.STATION_NAME, default_station(width=640, height=480).to_dict())
        with pytest.raises(InputError, match="wrong calibration"):
            Pipeline(archive).process(uids["back"], calibration=(gt.STATION_NAME, 2))


def test_bad_frames_are_processed_to_empty_results_with_reasons(settings: Settings) -> None:
    frames = {"black": np.zeros((604, 576), np.uint8), "white": np.full((604, 576), 255, np.uint8)}
    archive, uids = gt.archive_with_frames(settings, frames)
    with archive:
        pipeline = Pipeline(archive)
        for uid in uids.values():
            result = pipeline.process(uid)
            assert result.final is not None and len(result.final.vertices) == 0
            assert "no" in result.reason
            row, _ = pipeline.result(uid, "points")
            assert row.reason


def test_unprocessed_lists_acquisitions_without_a_successful_run(settings: Settings) -> None:
    frames = {"a": gt.rendering("back").image, "b": np.zeros((604, 576), np.uint8)}
    archive, uids = gt.archive_with_frames(settings, frames)
    with archive:
        pipeline = Pipeline(archive)
        assert pipeline.unprocessed() == [uids["a"], uids["b"]]
        pipeline.process(uids["b"], until="peaks")
        assert pipeline.unprocessed() == [uids["a"]]
        assert pipeline.unprocessed(patient="P1") == [uids["a"]]


def test_a_crash_between_file_and_row_is_healed_by_the_next_run(archived, monkeypatch) -> None:
    archive, uid = archived
    pipeline = Pipeline(archive)
    plan = pipeline.plan(uid, until="points")
    computation = pipeline.compute(plan)

    class Crash(BaseException):
        pass

    def crash(*_args, **_kwargs):
        raise Crash

    # files are written, then the catalogue transaction dies
    monkeypatch.setattr(archive, "session", crash)
    with pytest.raises(Crash):
        pipeline.commit(plan, computation)
    monkeypatch.undo()
    files = sorted((Path(archive.settings.archive) / "derived").rglob("*.h5"))
    assert len(files) == 5
    result = pipeline.process(uid, until="points")
    assert result.computed == 5
    assert sorted((Path(archive.settings.archive) / "derived").rglob("*.h5")) == files
    assert _count(archive, StageResult) == 5
    assert _count(archive, PipelineRun, status="done") == 1


def test_verify_explains_every_derived_file(archived) -> None:
    archive, uid = archived
    pipeline = Pipeline(archive)
    pipeline.process(uid, until="points")
    report = pipeline.verify()
    assert report.ok and report.frames_checked == 5 and report.acquisitions_checked == 1
    rows = pipeline.results(uid)
    root = Path(archive.settings.archive)
    # a computation whose row never made it
    plan = pipeline.plan(uid, until="points", params={"points": {"depth_limit": 500.0}})
    computation = pipeline.compute(plan)
    step = plan.steps[-1]
    pipeline.derived.write(
        uid,
        computation.records["points"],
        stage="points",
        plugin=step.plugin,
        plugin_version=step.version,
        params=step.params,
        params_hash=step.params_hash,
        chain_key=plan.keys[-1],
        input_checksum=plan.input_checksum,
    )
    assert [r.stage for r in rows[:4]] == ["peaks", "lines", "order", "numbers"]
    (root / rows[0].store_path).unlink()
    damaged = root / rows[1].store_path
    damaged.write_bytes(damaged.read_bytes()[:200])
    (damaged.parent / f"{damaged.name}.tmp-1-abcd").write_bytes(b"partial")
    problems = pipeline.verify().problems
    kinds = sorted(p.kind for p in problems)
    # order and numbers inherit the peaks' fields through the damaged lines file: they
    # cannot be read either, and say why
    assert kinds == ["corrupt", "corrupt", "corrupt", "missing", "orphaned", "temporary"]
    based = [p for p in problems if p.kind == "corrupt" and "its base is damaged" in p.detail]
    assert len(based) == 2
