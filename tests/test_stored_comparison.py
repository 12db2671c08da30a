"""Comparisons stored as stage results with inputs from two acquisitions: computed once,
reused, keyed by their inputs, verified with the archive, and protecting their inputs
(SQLite and PostgreSQL catalogues, real HDF5 files)."""

from __future__ import annotations

from functools import lru_cache

import pytest
from sqlalchemy import delete, select
from sqlalchemy.exc import IntegrityError

from rasterserver.archive import Archive
from rasterserver.catalog.models import StageResult, StageResultInput
from rasterserver.config import Settings
from rasterserver.errors import InputError, NotFoundError
from rasterserver.records_comparison import AsymmetryRecord, ComparisonRecord
from rasterserver.stored_comparison import (
    ASYMMETRY_STAGE,
    COMPARISON_STAGE,
    stored_asymmetry,
    stored_comparison,
)
from rasterserver.visit_comparison import compare_two, load_visit

PATIENT = "P-STORED"


@lru_cache(maxsize=1)
def _rendered() -> tuple:
    """Three rendered visits (once per test process: rendering is the slow part)."""
    from rasterserver.demo import simulate_visits

    return tuple(simulate_visits(3, supersample=1, progression=0.5))


@pytest.fixture
def archived(settings: Settings):
    """Two processed visits of one patient and an unprocessed third."""
    from rasterserver.optics import default_station
    from rasterserver.pipeline import Pipeline
    from rasterserver.simulated_visits import archive_visits

    with Archive.create(settings) as archive:
        rows = archive_visits(archive, _rendered(), station=default_station(), patient=PATIENT)
        pipeline = Pipeline(archive)
        for row in rows[:2]:
            for target in ("mesh", "analysis"):
                pipeline.process(row.uid, until=target)
        yield pipeline, [r.uid for r in rows]


def test_a_comparison_is_stored_once_and_reused(archived) -> None:
    pipeline, (first, second, _third) = archived
    a, b = load_visit(pipeline, first), load_visit(pipeline, second)
    made = stored_comparison(pipeline, a, b)
    assert not made.reused and not made.record.refused
    assert made.plugin == "comparison.landmark-icp"
    again = stored_comparison(pipeline, load_visit(pipeline, first), load_visit(pipeline, second))
    assert again.reused and again.result_id == made.result_id
    assert again.record.content_hash() == made.record.content_hash()
    # the first answer is the stored one to the memory order of its arrays (a product of a
    # Fortran-ordered transform differs in the last bit: a carried parameter would change)
    for name in ("transform", "start", "trunk", "distance"):
        first_array, later = getattr(made.record, name), getattr(again.record, name)
        assert first_array.strides == later.strides
    with pipeline.archive.session() as s:
        row = s.get(StageResult, made.result_id)
        assert row is not None and row.stage == COMPARISON_STAGE
        assert row.record_kind == ComparisonRecord.kind and row.run_id is None
        inputs = list(
            s.scalars(
                select(StageResultInput)
                .where(StageResultInput.result_id == made.result_id)
                .order_by(StageResultInput.position)
            )
        )
    roles = [i.role for i in inputs]
    assert roles == ["a.analysis", "a.mesh", "b.analysis", "b.mesh"]
    assert [i.input_id for i in inputs] == [r for _role, r, _sum in a.inputs + b.inputs]
    # the comparison's file is known to the archive: verify finds nothing wrong
    report = pipeline.verify()
    assert report.problems == []
    assert report.frames_checked == len(pipeline.results(first)) + len(pipeline.results(second))
    assert made.record.trunk.size == made.record.distance.size > 500
    # version 2 stores which trunk vertices were not compared (none on these visits)
    assert made.record.displaced is not None
    assert made.record.displaced.shape == made.record.trunk.shape
    assert (again.record.displaced == made.record.displaced).all()


def test_other_parameters_make_another_result(archived) -> None:
    pipeline, (first, second, _third) = archived
    a, b = load_visit(pipeline, first), load_visit(pipeline, second)
    one = stored_comparison(pipeline, a, b)
    other = stored_comparison(pipeline, a, b, params={"margin": 25.0})
    assert not other.reused and other.result_id != one.result_id
    assert other.record.parameter_table()["margin_mm"] == 25.0
    # fewer trunk vertices with the wider margin
    assert len(other.record.trunk) < len(one.record.trunk)
    with pytest.raises(InputError, match="margin"):
        stored_comparison(pipeline, a, b, params={"margin": -1.0})
    with pytest.raises(InputError):
        stored_comparison(pipeline, a, b, plugin="mesh.grid")


def test_an_input_cannot_be_deleted_from_under_a_comparison(archived) -> None:
    pipeline, (first, second, _third) = archived
    a, b = load_visit(pipeline, first), load_visit(pipeline, second)
    stored_comparison(pipeline, a, b)
    mesh_id = a.inputs[-1][1]
    with pytest.raises(IntegrityError), pipeline.archive.session() as s:
        s.execute(delete(StageResult).where(StageResult.id == mesh_id))
        s.flush()


def test_compare_two_reports_the_stored_result(archived) -> None:
    pipeline, (first, second, third) = archived
    one = compare_two(pipeline, second, first)
    two = compare_two(pipeline, first, second)
    assert one.document["provenance"]["reused"] is False
    assert two.document["provenance"]["reused"] is True
    assert one.document["registration"] == two.document["registration"]
    assert one.document["distance"] == two.document["distance"]
    with pytest.raises(NotFoundError, match="process"):
        compare_two(pipeline, first, third)


def test_a_visit_without_geometry_is_refused(archived) -> None:
    pipeline, (first, second, _third) = archived
    a = load_visit(pipeline, first)
    broken = type(a)(a.uid, a.acquired_at, None, None, "no trunk found", a.acquisition_id)
    with pytest.raises(InputError, match="no trunk found"):
        stored_comparison(pipeline, broken, load_visit(pipeline, second))


def test_trends_show_an_unprocessed_visit_as_a_gap(archived) -> None:
    from rasterserver.visit_comparison import trend_visits

    pipeline, (first, second, third) = archived
    rows = trend_visits(pipeline, PATIENT)
    assert [uid for uid, _when, _p in rows] == [first, second, third]
    assert rows[0][2] is not None and rows[1][2] is not None
    assert rows[2][2] is None  # not processed: a gap, not a 404 for the whole patient


def test_a_visits_asymmetry_map_is_stored_once(archived) -> None:
    pipeline, (first, _second, _third) = archived
    visit = load_visit(pipeline, first)
    made = stored_asymmetry(pipeline, visit)
    assert isinstance(made.record, AsymmetryRecord) and not made.record.refused
    assert made.plugin == "asymmetry.mirror-icp" and not made.reused
    assert len(made.record.trunk) == len(made.record.asymmetry) > 500
    again = stored_asymmetry(pipeline, load_visit(pipeline, first))
    assert again.reused and again.result_id == made.result_id
    with pipeline.archive.session() as s:
        row = s.get(StageResult, made.result_id)
        assert row is not None and row.stage == ASYMMETRY_STAGE
        roles = list(
            s.scalars(
                select(StageResultInput.role)
                .where(StageResultInput.result_id == made.result_id)
                .order_by(StageResultInput.position)
            )
        )
    assert roles == ["analysis", "mesh"]
    # a report of the two visits reuses it and stores the other visit's
    two = compare_two(pipeline, first, _second)
    assert two.document["asymmetry"][first]["provenance"]["reused"] is True
    assert two.document["asymmetry"][_second]["provenance"]["reused"] is False
    assert pipeline.verify().problems == []
