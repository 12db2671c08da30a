"""VP carried between archived visits (:mod:`rasterserver.carried_analysis`), in process; the
installed command's view is in ``tests/commands/test_compare.py`` (SQLite and PostgreSQL
catalogues, real HDF5 files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rasterserver.archive import Archive
from rasterserver.carried_analysis import carried_parameters, with_carried
from rasterserver.config import Settings
from rasterserver.pipeline import Pipeline

KEPT = Path(__file__).parent / "data" / "scenes"


def test_a_visits_own_values_are_never_replaced() -> None:
    own = {"pelvic_tilt_mm": {"value": 1.0, "unit": "mm", "spread": None}}
    carried = {
        "pelvic_tilt_mm": {"value": 9.0, "unit": "mm", "spread": None},
        "surface_rotation_rms_deg": {"value": 2.5, "unit": "deg", "spread": None},
    }
    merged = with_carried(own, carried, "uid-2")
    assert merged["pelvic_tilt_mm"] == own["pelvic_tilt_mm"]
    assert merged["surface_rotation_rms_deg"]["vp_carried_from"] == "uid-2"
    assert with_carried(None, {}, "uid-2") == {}


@pytest.fixture
def archive(settings: Settings):
    with Archive.create(settings) as archive:
        yield archive


def processed(archive: Archive, roles: str) -> tuple[Pipeline, list[str]]:
    """Processed acquisitions of one patient, oldest first, from the kept frames of clinic
    tuning person 1 (``A``: hair over the nape, no VP; ``E``: VP found)."""
    from rasterserver.simulated_visits import SimulatedVisit, archive_visits
    from rasterserver.simulator.body import clinic_station, random_body

    kept = {role: np.load(KEPT / f"person-1-{role}.npz") for role in set(roles)}
    first = kept[roles[0]]
    station = clinic_station(int(first["seed"]), str(first["code"]))
    back = random_body(1).back
    rows = archive_visits(
        archive,
        [SimulatedVisit(back, kept[r]["image"]) for r in roles],
        station=station,
        patient="P-1",
        station_name="clinic",
    )
    pipeline = Pipeline(archive)
    for row in rows:
        pipeline.process(row.uid, until="mesh")
        pipeline.process(row.uid, until="analysis")
    return pipeline, [r.uid for r in rows]


def test_two_visits_without_vp_carry_nothing_and_say_why(archive, tmp_path: Path) -> None:
    from rasterserver.visit_comparison import compare_visits

    pipeline, uids = processed(archive, "AA")
    lines: list[str] = []
    document = compare_visits(pipeline, uids, tmp_path / "out", log=lines.append)
    assert "refused" not in document["pairs"][0]  # registered from the dimples alone
    assert document["carried_vp"] == {
        uid: {"refused": "no other visit found its VP"} for uid in uids
    }
    assert "VP carried to 0 of 2 visits without their own" in lines
    assert carried_parameters(pipeline, [], []) == {}


def test_a_patients_trends_carry_vp_to_the_visit_without(archive) -> None:
    from rasterserver.trends import TrendVisit, trends
    from rasterserver.visit_comparison import trend_visits

    pipeline, (first, second) = processed(archive, "AE")
    visits = trend_visits(pipeline, "P-1")
    assert [v[0] for v in visits] == [first, second]
    carried = visits[0][2]["lateral_deviation_rms_mm"]
    assert carried["vp_carried_from"] == second
    assert "trunk_length" not in visits[0][2] and "trunk_length" in visits[1][2]
    table = {r["parameter"]: r for r in trends([TrendVisit(*v) for v in visits])}
    row = table["surface_rotation_rms_deg"]["visits"]
    assert row[0]["vp_carried_from"] == second and row[1]["vp_carried_from"] is None
    assert row[1]["change"] is not None
    # asked again, the comparison the carrying needed is reused, not stored twice
    from sqlalchemy import func, select

    from rasterserver.catalog.models import StageResult

    def comparisons() -> int:
        with archive.session() as s:
            query = select(func.count()).where(StageResult.stage == "comparison")
            return int(s.scalar(query) or 0)

    stored = comparisons()
    assert stored == 1
    assert trend_visits(pipeline, "P-1") == visits
    assert comparisons() == stored


def test_compare_carries_past_partners_without_vp_from_the_nearest_that_found_it(
    archive, tmp_path: Path
) -> None:
    # E (VP) then A three times (no VP): the pairs are E-A1, A1-A2, A2-A3 and E-A3; A2's
    # partners found no VP, so it is registered with E, the nearest visit that did
    from rasterserver.catalog.models import StageResult
    from rasterserver.visit_comparison import compare_visits

    pipeline, uids = processed(archive, "EAAA")
    document = compare_visits(pipeline, uids, tmp_path / "out")
    assert len(document["pairs"]) == 4
    carried = document["carried_vp"]
    assert {uid: c.get("from") for uid, c in carried.items()} == dict.fromkeys(uids[1:], uids[0])
    with archive.session() as s:
        stored = s.query(StageResult).filter(StageResult.stage == "comparison").count()
    assert stored == 5  # the four pairs and E-A2, made for the carrying
