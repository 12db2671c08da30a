"""The trunk in a height field: outline, centre, arms apart, cut-off backs, too little surface."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.trunk import find_trunk

SPACING = 3.0


def _body(*, cut: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A trunk (neck, shoulders, waist, hips) centred at x = 12 mm, arms 20 mm beside it."""
    y, x = np.mgrid[-300:300:SPACING, -260:260:SPACING]
    t = (y + 300.0) / 600.0
    half = np.interp(t, [0.0, 0.15, 0.25, 0.6, 1.0], [55.0, 60.0, 170.0, 125.0, 160.0])
    off = x - 12.0
    z = np.where(np.abs(off) <= half, 20.0 + (off / 40.0) ** 2, np.nan)
    arm = (np.abs(np.abs(off) - (half + 55.0)) < 35.0) & (t > 0.35)
    z = np.where(arm, 90.0, z)
    if cut is not None:
        z[:, x[0] > cut] = np.nan
    return x, y, z


def test_outline_centre_and_extent() -> None:
    x, _, z = _body()
    trunk = find_trunk(z, SPACING)
    assert trunk.found and not trunk.cut and trunk.reason == ""
    assert trunk.top == 0 and trunk.bottom == z.shape[0] - 1
    centre_x = x[0, 0] + SPACING * trunk.centre[trunk.top : trunk.bottom + 1]
    np.testing.assert_allclose(centre_x, 12.0, atol=1.6)
    # the arms are not trunk: they are separated by a gap (and a depth jump)
    assert not (trunk.mask & (z == 90.0)).any()
    assert 110.0 < trunk.reference_half_width() < 140.0


def test_half_a_back_is_recognised_as_cut() -> None:
    _, _, z = _body(cut=12.0)
    trunk = find_trunk(z, SPACING)
    assert trunk.found and trunk.cut == "right"


def test_too_little_surface() -> None:
    z = np.full((100, 100), np.nan)
    z[40:50, 40:50] = 1.0
    trunk = find_trunk(z, SPACING)
    assert not trunk.found and "cm²" in trunk.reason
    assert not find_trunk(np.full((10, 10), np.nan), SPACING).found


def test_holes_inside_the_back_do_not_cut_it() -> None:
    # Two strips of lost cells along the lumbar furrow, 12 mm apart, over 60 mm of height.
    x, y, z = _body()
    for centre in (6.0, 18.0):
        z[(np.abs(x - centre) < 4.0) & (y > 100.0) & (y < 160.0)] = np.nan
    trunk = find_trunk(z, SPACING)
    assert trunk.top == 0 and trunk.bottom == z.shape[0] - 1
    rows = (y[:, 0] > 100.0) & (y[:, 0] < 160.0)
    assert (trunk.half_width[rows] > 100.0).all()
