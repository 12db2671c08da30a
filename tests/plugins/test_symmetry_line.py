"""Hierholzer's symmetry line: the mirror axis of every profile, against exact axes and truth."""

from __future__ import annotations

import numpy as np
import pytest
from back_surfaces import back
from rasterserver_plugins.curvature import surface_curvature
from rasterserver_plugins.level_frame import LevelGrid
from rasterserver_plugins.symmetry_line import (
    EDGE_ROOM,
    SymmetryLine,
    edge_room_reason,
    find_symmetry_line,
    profile_asymmetry,
)
from rasterserver_plugins.trunk import find_trunk

SPACING = 3.0


def _axis_path(y: np.ndarray) -> np.ndarray:
    """A scoliotic spinal line: a right thoracic and a left lumbar curve (mm)."""
    return 30.0 * np.exp(-0.5 * ((y + 60.0) / 70.0) ** 2) - 15.0 * np.exp(
        -0.5 * ((y - 150.0) / 50.0) ** 2
    )


def _sheared_back() -> LevelGrid:
    """Cross-sections symmetric about a line that wanders sideways with the height."""
    y, x = np.mgrid[-300:300:SPACING, -200:200:SPACING]
    u = x - _axis_path(y)
    relief = -4.0 * np.exp(-0.5 * (u / 9.0) ** 2) + 3.0 * np.exp(
        -0.5 * ((np.abs(u) - 35) / 15) ** 2
    )
    z = 50.0 + (u / 30.0) ** 2 - relief
    return LevelGrid(float(x[0, 0]), float(y[0, 0]), SPACING, z)


def test_asymmetry_is_zero_about_the_mirror_axis() -> None:
    nx = 41
    u = np.arange(nx) - 17.5  # symmetric about column 17.5: half-cell axis 35
    h = np.exp(-0.5 * (u / 4.0) ** 2)
    a = 0.3 * np.cos(u / 3.0)
    features = np.stack([h, a, 0.2 * np.sign(u) * np.abs(u) / 10.0])[:, None, :]
    table = profile_asymmetry(features, reach=16)
    assert table.shape == (1, 2 * nx - 1)
    assert int(np.nanargmin(table[0])) == 35
    assert table[0, 35] == pytest.approx(0.0, abs=1e-12)


def test_follows_a_wandering_axis() -> None:
    grid = _sheared_back()
    curv = surface_curvature(grid.z, SPACING, sigma=5.0)
    top = np.array([_axis_path(np.array(-250.0)), -250.0, 50.0])
    bottom = np.array([_axis_path(np.array(250.0)), 250.0, 50.0])
    line = find_symmetry_line(grid, curv, top, bottom, half_width=130.0)
    assert line.found
    error = line.x - _axis_path(line.y)
    assert np.sqrt(np.mean(error**2)) < 0.5 and np.abs(error).max() < 1.0


def test_bridges_unmeasured_cells() -> None:
    grid = _sheared_back()
    z = grid.z.copy()
    z[100:130, :] = np.nan  # a band of profiles without data
    z[:, 70:72] = np.nan  # and a hole on one side, close to the axis
    holed = LevelGrid(grid.x0, grid.y0, SPACING, z)
    curv = surface_curvature(z, SPACING, sigma=5.0)
    top = np.array([_axis_path(np.array(-250.0)), -250.0, 50.0])
    bottom = np.array([_axis_path(np.array(250.0)), 250.0, 50.0])
    line = find_symmetry_line(holed, curv, top, bottom, half_width=130.0)
    assert line.found and np.isfinite(line.x).all() and np.isfinite(line.z).all()
    error = line.x - _axis_path(line.y)
    assert np.sqrt(np.mean(error**2)) < 1.5


@pytest.mark.parametrize("name", ["normal", "severe"])
def test_against_the_spinous_process_line(name: str) -> None:
    surface, truth = back(name)
    grid = LevelGrid(surface.x0, surface.y0, surface.spacing, surface.z)
    curv = surface_curvature(grid.z, grid.spacing, sigma=5.0)
    vp, dm = truth["landmarks"]["VP"], truth["landmarks"]["DM"]
    line = find_symmetry_line(grid, curv, vp, dm, half_width=120.0)
    skin = truth["spine"]["skin"]
    error = line.x - np.interp(line.y, skin[:, 1], skin[:, 0])
    assert np.sqrt(np.mean(error**2)) < 1.0


def test_too_short_a_line_is_refused() -> None:
    grid = _sheared_back()
    curv = surface_curvature(grid.z, SPACING, sigma=5.0)
    line = find_symmetry_line(
        grid, curv, np.array([0.0, 0.0, 0.0]), np.array([0.0, 9.0, 0.0]), half_width=130.0
    )
    assert not line.found and "5 profiles" in line.reason


def test_a_line_along_the_trunks_edge_is_refused() -> None:
    # a 300 mm wide trunk (x -150 to 150): a line at x = 0 has room; one that runs to within
    # 10 mm of the left edge at one height (14 mm is 0.1 half-widths) is refused there
    _y, x = np.mgrid[-300:300:3.0, -200:200:3.0]
    grid = LevelGrid(
        -200.0, -300.0, 3.0, np.where(np.abs(x) <= 150.0, 40.0 + (x / 30.0) ** 2, np.nan)
    )
    trunk = find_trunk(grid.z, grid.spacing)
    ys = np.arange(-150.0, 150.0, 3.0)

    def line(xs: np.ndarray) -> SymmetryLine:
        return SymmetryLine(x=xs, y=ys, z=0 * ys, asymmetry=0 * ys, raw_x=xs)

    assert edge_room_reason(line(0 * ys), grid, trunk, EDGE_ROOM) == ""
    bent = np.where(np.abs(ys) < 20.0, -140.0, 0.0)
    why = edge_room_reason(line(bent), grid, trunk, EDGE_ROOM)
    assert "from the measured trunk's edge" in why and "at height" in why
    assert edge_room_reason(line(bent), grid, trunk, 0.0) == ""
