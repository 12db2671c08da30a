"""Curvature of height fields: exact on analytic surfaces, signs, borders and holes."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.curvature import fit_quadric_at, surface_curvature, window_support

SPACING = 3.0


def _grid(half_x: float = 240.0, half_y: float = 300.0) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[-half_y:half_y:SPACING, -half_x:half_x:SPACING]
    return x, y


def _interior(valid: np.ndarray, cells: int) -> np.ndarray:
    """Cells at least ``cells`` away from every unmeasured cell and the grid's border."""
    from scipy.ndimage import binary_erosion

    return binary_erosion(valid, iterations=cells, border_value=False)


def test_plane_has_no_curvature() -> None:
    x, y = _grid()
    c = surface_curvature(0.3 * x - 0.2 * y + 5.0, SPACING, sigma=8.0)
    ok = np.isfinite(c.mean)
    # only the grid's corners, where under half the window is measured, are left out
    assert ok.mean() > 0.99 and (c.support[~ok] < 0.45).all()
    assert np.abs(c.mean[ok]).max() < 1e-12
    assert np.abs(c.gaussian[ok]).max() < 1e-12
    np.testing.assert_allclose(c.zx[ok], 0.3, atol=1e-12)
    np.testing.assert_allclose(c.zy[ok], -0.2, atol=1e-12)


@pytest.mark.parametrize("sigma", [5.0, 10.0])
def test_sphere_bump_towards_the_camera(sigma: float) -> None:
    # The cap of a sphere of radius R seen from the camera: its nearest point is the centre.
    radius = 200.0
    x, y = _grid()
    r2 = x * x + y * y
    z = np.where(r2 < (0.6 * radius) ** 2, -np.sqrt(np.maximum(radius**2 - r2, 0.0)), np.nan)
    c = surface_curvature(z, SPACING, sigma=sigma)
    inner = _interior(np.isfinite(z), int(3 * sigma / SPACING) + 1)
    # convex towards the camera: H > 0, K > 0, both principal curvatures 1/R
    np.testing.assert_allclose(c.mean[inner] * radius, 1.0, rtol=0.01)
    np.testing.assert_allclose(c.gaussian[inner] * radius**2, 1.0, rtol=0.02)
    np.testing.assert_allclose(c.k1[inner] * radius, 1.0, rtol=0.02)
    np.testing.assert_allclose(c.k2[inner] * radius, 1.0, rtol=0.02)
    # near the cut border the one-sided fits stay sane: within 10 %
    near = np.isfinite(c.mean) & ~inner
    np.testing.assert_allclose(c.mean[near] * radius, 1.0, rtol=0.1)


def test_dimple_is_concave() -> None:
    radius = 150.0
    x, y = _grid()
    r2 = x * x + y * y
    z = np.where(r2 < (0.5 * radius) ** 2, np.sqrt(np.maximum(radius**2 - r2, 0.0)), np.nan)
    c = surface_curvature(z, SPACING, sigma=6.0)
    inner = _interior(np.isfinite(z), 8)
    np.testing.assert_allclose(c.mean[inner] * radius, -1.0, rtol=0.01)
    assert (c.gaussian[inner] > 0).all()


def test_cylinder_principal_curvatures_and_directions() -> None:
    radius = 180.0
    x, _ = _grid()
    z = np.where(np.abs(x) < 0.7 * radius, -np.sqrt(np.maximum(radius**2 - x * x, 0.0)), np.nan)
    c = surface_curvature(z, SPACING, sigma=6.0)
    inner = _interior(np.isfinite(z), 8)
    np.testing.assert_allclose(c.k1[inner] * radius, 1.0, rtol=0.01)
    np.testing.assert_allclose(c.k2[inner] * radius, 0.0, atol=1e-6)
    np.testing.assert_allclose(c.mean[inner] * 2 * radius, 1.0, rtol=0.01)
    np.testing.assert_allclose(c.gaussian[inner], 0.0, atol=1e-9)
    # the curved direction runs across (along x)
    np.testing.assert_allclose(c.direction[inner], 0.0, atol=1e-6)


def test_saddle() -> None:
    radius = 250.0
    x, y = _grid()
    z = (x * x - y * y) / (2 * radius)  # curved up along x, down along y
    c = surface_curvature(z, SPACING, sigma=10.0)
    i, j = np.argwhere((np.abs(x) < 1e-9) & (np.abs(y) < 1e-9))[0]
    assert c.mean[i, j] == pytest.approx(0.0, abs=1e-9)
    assert c.gaussian[i, j] * radius**2 == pytest.approx(-1.0, rel=1e-6)
    assert c.k1[i, j] * radius == pytest.approx(1.0, rel=1e-6)
    assert c.k2[i, j] * radius == pytest.approx(-1.0, rel=1e-6)
    assert c.direction[i, j] == pytest.approx(0.0, abs=1e-9)
    # the quadric saddle is fitted exactly everywhere: K = -1/(R² W⁴) by the Monge formula
    w2 = 1 + (x / radius) ** 2 + (y / radius) ** 2
    ok = np.isfinite(c.gaussian) & _interior(np.ones_like(z, bool), 12)
    np.testing.assert_allclose(c.gaussian[ok], -1.0 / (radius**2 * w2[ok] ** 2), rtol=1e-6)


def test_holes_do_not_spread_garbage() -> None:
    # A paraboloid with a hole: around the hole the one-sided fits are still exact.
    x, y = _grid()
    z = (x * x + y * y) / 400.0
    z[(np.abs(x) < 30) & (np.abs(y - 60) < 30)] = np.nan
    c = surface_curvature(z, SPACING, sigma=8.0)
    assert np.isnan(c.mean[np.isnan(z)]).all()
    ok = np.isfinite(c.mean)
    w2 = 1 + (x / 200.0) ** 2 + (y / 200.0) ** 2
    expected = (2 + (x / 200.0) ** 2 + (y / 200.0) ** 2) / (400.0 * w2**1.5)
    np.testing.assert_allclose(c.mean[ok], expected[ok], rtol=1e-6)


def test_narrow_strips_and_empty_input_give_nan() -> None:
    z = np.full((40, 40), np.nan)
    z[20, :] = 1.0  # a single row: no quadric
    c = surface_curvature(z, SPACING, sigma=6.0)
    assert np.isnan(c.mean).all()
    assert np.isnan(surface_curvature(np.full((5, 5), np.nan), SPACING).mean).all()
    assert surface_curvature(np.zeros((0, 0)), SPACING).mean.shape == (0, 0)


def test_fit_quadric_at_arbitrary_points() -> None:
    x, y = _grid()
    z = 1 + 0.2 * x - 0.1 * y + 0.01 * x * x + 0.002 * x * y - 0.003 * y * y
    cols = np.array([80.3, 20.0])
    rows = np.array([100.7, 3.2])
    coef = fit_quadric_at(z, SPACING, cols, rows, (20.0, 8.0))
    px = x[0, 0] + SPACING * cols
    py = y[0, 0] + SPACING * rows
    np.testing.assert_allclose(coef[:, 1], 0.2 + 0.02 * px + 0.002 * py, rtol=1e-9)
    np.testing.assert_allclose(coef[:, 2], -0.1 + 0.002 * px - 0.006 * py, rtol=1e-9)
    np.testing.assert_allclose(coef[:, 3], 0.01, rtol=1e-9)
    # a window turned with a leaning trunk fits the same quadric, in the same axes
    for angle in (0.1, -0.4):
        turned = fit_quadric_at(z, SPACING, cols, rows, (20.0, 8.0), angle=angle)
        np.testing.assert_allclose(turned, coef, rtol=1e-7, atol=1e-9)
    # far outside the grid there is nothing to fit
    assert np.isnan(fit_quadric_at(z, SPACING, np.array([-100.0]), np.array([5.0]), (9, 9))).all()


def test_window_support_per_half() -> None:
    z = np.zeros((60, 80))
    z[:, 40:] = np.nan  # the right half of the grid is not measured
    cols, rows = np.array([20.0, 39.5, 60.0]), np.array([30.0, 30.0, 30.0])
    share = window_support(z, 3.0, cols, rows, (25.0 / 3.0, 6.0 / 3.0))
    np.testing.assert_allclose(share[0], [1.0, 1.0], atol=1e-12)  # the window is inside
    np.testing.assert_allclose(share[1], [1.0, 0.0], atol=1e-12)  # one side wholly missing
    np.testing.assert_allclose(share[2], [0.0, 0.0], atol=1e-12)
    # turned by 90 degrees, the halves lie above and below: both half measured
    turned = window_support(z, 3.0, cols[1:2], rows[1:2], (6.0, 2.0), angle=np.pi / 2)
    assert 0.3 < turned[0, 0] < 0.7 and 0.3 < turned[0, 1] < 0.7
    # outside the grid counts as not measured
    edge = window_support(np.zeros((60, 80)), 3.0, np.array([0.0]), np.array([30.0]), (9.0, 3.0))
    assert edge[0, 0] < 0.05 and edge[0, 1] == pytest.approx(1.0)
