"""The level frame: axes from gravity, and the surface resampled onto a plumb grid."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rasterserver_plugins.level_frame import LevelFrame, LevelGrid, bilinear


def _world_grid(fn, spacing=3.0):
    y, x = np.mgrid[-200:200:spacing, -150:150:spacing]
    return float(x[0, 0]), float(y[0, 0]), spacing, fn(x, y)


def test_default_station_is_the_world_frame() -> None:
    frame = LevelFrame.from_gravity(np.array([0.0, 1.0, 0.0]))
    assert frame.is_identity
    x0, y0, s, z = _world_grid(lambda x, y: x * x / 300.0)
    grid = frame.level_grid(x0, y0, s, z)
    assert grid.z is z and (grid.x0, grid.y0) == (x0, y0)


@pytest.mark.parametrize(
    "gravity",
    [(math.sin(0.1), math.cos(0.1), 0.0), (0.0, math.cos(0.15), math.sin(0.15)), (1.0, 0.0, 0.0)],
)
def test_axes_are_right_handed_with_y_along_gravity(gravity: tuple[float, float, float]) -> None:
    g = np.array(gravity)
    rot = LevelFrame.from_gravity(2.0 * g).rotation  # any length
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    np.testing.assert_allclose(rot[1], g / np.linalg.norm(g))
    assert rot[2, 1] * g[1] + rot[2, 0] * g[0] + rot[2, 2] * g[2] == pytest.approx(0.0, abs=1e-12)
    assert rot[2, 2] > 0  # the sagittal axis points away from the camera


@pytest.mark.parametrize("gravity", [(0.0, 0.0, 0.0), (np.nan, 1.0, 0.0), (0.0, 0.2, 1.0)])
def test_unusable_gravity_is_refused(gravity: tuple[float, float, float]) -> None:
    with pytest.raises(ValueError, match=r"gravity|camera looks"):
        LevelFrame.from_gravity(np.array(gravity))


def test_resampled_surface_lies_on_the_world_surface() -> None:
    # A camera pitched 8° down: gravity has a Z component.
    a = math.radians(8.0)
    frame = LevelFrame.from_gravity(np.array([0.0, math.cos(a), math.sin(a)]))
    x0, y0, s, z = _world_grid(lambda x, y: 500.0 + (x * x + 0.5 * y * y) / 600.0)
    grid = frame.level_grid(x0, y0, s, z)
    jj, ii = np.meshgrid(np.arange(grid.shape[1]), np.arange(grid.shape[0]))
    ok = np.isfinite(grid.z)
    assert ok.mean() > 0.8
    level = np.column_stack([grid.x_of(jj[ok]), grid.y_of(ii[ok]), grid.z[ok]])
    world = frame.to_world(level)
    on_surface = bilinear(z, (world[:, 0] - x0) / s, (world[:, 1] - y0) / s)
    np.testing.assert_allclose(world[:, 2], on_surface, atol=1e-3)
    # a plane upright in the level frame (z' = 550) comes out flat
    ez = frame.rotation[2]
    _, _, _, tilted = _world_grid(lambda x, y: (550.0 - ez[0] * x - ez[1] * y) / ez[2])
    flat = frame.level_grid(x0, y0, s, tilted)
    np.testing.assert_allclose(flat.z[np.isfinite(flat.z)], 550.0, atol=1e-6)


def test_points_round_trip() -> None:
    frame = LevelFrame.from_gravity(np.array([0.05, 1.0, 0.08]))
    p = np.array([[1.0, 2.0, 3.0], [-40.0, 100.0, 7.0]])
    np.testing.assert_allclose(frame.to_world(frame.to_level(p)), p)


def test_bilinear_is_nan_next_to_holes_and_outside() -> None:
    z = np.arange(16, dtype=float).reshape(4, 4)
    z[1, 1] = np.nan
    assert bilinear(z, np.array([2.5]), np.array([2.5]))[0] == pytest.approx(12.5)
    assert np.isnan(bilinear(z, np.array([0.5]), np.array([0.5]))[0])
    assert np.isnan(bilinear(z, np.array([-0.1]), np.array([2.0]))[0])
    grid = LevelGrid(10.0, 20.0, 2.0, z)
    assert grid.point(2.5, 2.5) is not None and grid.point(0.5, 0.5) is None
