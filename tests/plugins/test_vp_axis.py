"""VP checked against the symmetry axis below it: a candidate on the spine is kept, a
shoulder's convex point beside it is refused, an unmeasurable axis decides nothing; and
against DM: a point farther beside it than a trunk imbalance is refused."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.curvature import surface_curvature
from rasterserver_plugins.landmarks import Landmark
from rasterserver_plugins.level_frame import LevelGrid
from rasterserver_plugins.vp_axis import (
    MAX_IMBALANCE,
    MAX_OFFSET,
    axis_offset,
    check_confidence,
    check_imbalance,
    check_vertebra_prominens,
)

SPACING = 3.0
AXIS = 12.0  # the spine's x (mm)


def _upper_back() -> LevelGrid:
    """Profiles symmetric about x = AXIS (a spinous furrow between two muscle ridges), with
    a round shoulder bump at x = AXIS + 80 that breaks the symmetry locally."""
    y, x = np.mgrid[-150:150:SPACING, -200:200:SPACING]
    u = x - AXIS
    relief = -4.0 * np.exp(-0.5 * (u / 9.0) ** 2) + 3.0 * np.exp(
        -0.5 * ((np.abs(u) - 35) / 15) ** 2
    )
    shoulder = 6.0 * np.exp(-0.5 * (((x - AXIS - 80.0) / 12.0) ** 2 + ((y + 60.0) / 12.0) ** 2))
    z = 50.0 + (u / 30.0) ** 2 - relief - shoulder
    return LevelGrid(float(x[0, 0]), float(y[0, 0]), SPACING, z)


def _vp(x: float, y: float = -60.0) -> Landmark:
    return Landmark("VP", np.array([x, y, 50.0]), 0.9)


def test_a_candidate_on_the_axis_is_kept_and_a_shoulders_point_refused() -> None:
    grid = _upper_back()
    curv = surface_curvature(grid.z, SPACING, sigma=5.0)
    on_spine = _vp(AXIS + 3.0)
    assert abs(axis_offset(grid, curv, on_spine.point, 130.0) + 3.0) < 2.0
    assert check_vertebra_prominens(grid, curv, on_spine, 130.0) is on_spine
    shoulder = _vp(AXIS + 80.0)
    offset = axis_offset(grid, curv, shoulder.point, 130.0)
    assert abs(offset) > MAX_OFFSET  # off its own axis (the spine's or none near it)
    refused = check_vertebra_prominens(grid, curv, shoulder, 130.0)
    assert not refused.found and refused.confidence == 0.0
    assert "beside the back's symmetry axis below it" in refused.reason
    # the limit is the caller's: a loose one keeps it
    assert check_vertebra_prominens(grid, curv, shoulder, 130.0, max_offset=200.0).found


def test_an_unmeasured_axis_or_a_missing_vp_decides_nothing() -> None:
    grid = _upper_back()
    z = grid.z.copy()
    z[int((-60.0 + 150.0) / SPACING) :, :] = np.nan  # nothing measured below the candidate
    blind = LevelGrid(grid.x0, grid.y0, SPACING, z)
    curv = surface_curvature(blind.z, SPACING, sigma=5.0)
    shoulder = _vp(AXIS + 80.0)
    assert np.isnan(axis_offset(blind, curv, shoulder.point, 130.0))
    assert check_vertebra_prominens(blind, curv, shoulder, 130.0) is shoulder
    missing = Landmark("VP", None, 0.0, "no convex point")
    assert check_vertebra_prominens(blind, curv, missing, 130.0) is missing


def test_vp_farther_beside_dm_than_a_trunk_imbalance_is_refused() -> None:
    dm = Landmark("DM", np.array([4.0, 210.0, 30.0]), 0.9)
    near = Landmark("VP", np.array([4.0 + 45.0, -230.0, 0.0]), 0.8)
    assert check_imbalance(near, dm) is near  # 45 mm: a decompensated back, kept
    far = Landmark("VP", np.array([4.0 - 60.0, -230.0, 0.0]), 1.0)
    refused = check_imbalance(far, dm)
    assert refused.point is None and refused.confidence == 0.0
    assert "60 mm beside DM" in refused.reason and "vp_max_imbalance" in refused.reason
    assert check_imbalance(far, dm, max_imbalance=70.0) is far  # the limit raised
    missing = Landmark("DM", None, 0.0, "no dimples")
    assert check_imbalance(far, missing) is far  # without DM nothing to judge
    assert MAX_IMBALANCE == 50.0


def test_a_vp_below_the_least_confidence_is_refused_with_its_confidence() -> None:
    weak = Landmark("VP", np.array([-51.0, -135.0, -47.6]), 0.27)
    strong = Landmark("VP", np.array([4.0, -210.0, 30.0]), 0.70)
    assert check_confidence(weak) is weak  # 0: no check
    refused = check_confidence(weak, min_confidence=0.5)
    assert refused.point is None and refused.confidence == 0.0
    assert "confidence 0.27, below 0.50" in refused.reason
    assert check_confidence(strong, min_confidence=0.5) is strong
    missing = Landmark("VP", None, 0.0, "no convex point")
    assert check_confidence(missing, min_confidence=0.5) is missing
