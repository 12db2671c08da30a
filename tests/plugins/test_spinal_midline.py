"""Surface rotation and the vertebral-body midline: exact cases and the simulator's truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from back_surfaces import GRAVITY, back, mirrored
from rasterserver_plugins.back_shape import analyse_back
from rasterserver_plugins.level_frame import LevelGrid
from rasterserver_plugins.spinal_midline import (
    axial_rotation,
    body_depth,
    line_normals,
    spinal_midline,
    surface_rotation,
)
from rasterserver_plugins.symmetry_line import SymmetryLine

SPACING = 3.0


def _rotated_back(phi_deg: float) -> LevelGrid:
    """Symmetric cross-sections (a furrow on a rounded back) turned by ``phi`` about the
    furrow's bottom at x = 0, as the simulator turns the trunk about the spinous processes."""
    phi = math.radians(phi_deg)
    s = np.linspace(-250.0, 250.0, 2001)
    f = s * s / 400.0 - 4.0 * np.exp(-0.5 * (s / 9.0) ** 2)
    f0 = -4.0
    x = s * math.cos(phi) + (f - f0) * math.sin(phi)
    z = f0 - s * math.sin(phi) + (f - f0) * math.cos(phi)  # + turns +x towards the camera
    cols = np.arange(-150.0, 150.0 + SPACING, SPACING)
    row = np.interp(cols, x, z)
    return LevelGrid(float(cols[0]), -300.0, SPACING, 100.0 + np.tile(row, (200, 1)))


def _straight_line(grid: LevelGrid) -> SymmetryLine:
    y = grid.y_of(np.arange(20, 180))
    x = np.zeros_like(y)
    z = grid.depth(x, y)
    return SymmetryLine(x=x, y=y, z=z, asymmetry=np.zeros_like(y), raw_x=x)


@pytest.mark.parametrize("phi", [-12.0, 0.0, 5.0, 20.0])
def test_rotation_of_a_turned_cross_section(phi: float) -> None:
    grid = _rotated_back(phi)
    line = _straight_line(grid)
    vp = np.array([0.0, line.y[0], line.z[0]])
    dm = np.array([0.0, line.y[-1], line.z[-1]])
    normals = line_normals(grid, line, vp, dm)
    rotation = surface_rotation(normals)
    # a turned furrow and rounded back bias the smoothed normal by a few per cent
    np.testing.assert_allclose(rotation, phi, atol=0.1 + 0.04 * abs(phi))
    np.testing.assert_allclose(axial_rotation(normals, vp, dm), rotation, atol=1e-9)
    mid = spinal_midline(line, normals, vp, dm)
    # the body centres lie d·sin(φ) beside the spinous processes, on the turned side
    expected = mid.depth * np.sin(np.radians(rotation))
    np.testing.assert_allclose(mid.lateral_deviation, expected, atol=0.05)
    np.testing.assert_allclose(
        mid.points[:, 2] - line.z, mid.depth * np.cos(np.radians(rotation)), atol=0.5
    )


def test_a_leaning_trunk_turns_the_normal_but_not_the_bodies() -> None:
    # A straight back whose skin slopes backwards going down (0.3), leaning 5° sideways: the
    # horizontal part of the normal turns by about -0.3·sin(5°), the vertebrae do not.
    lean = math.radians(5.0)
    y, x = np.mgrid[-300:300:SPACING, -200:200:SPACING]
    xb = x * math.cos(lean) + y * math.sin(lean)
    yb = -x * math.sin(lean) + y * math.cos(lean)
    z = 100.0 + xb * xb / 400.0 - 4.0 * np.exp(-0.5 * (xb / 9.0) ** 2) - 0.3 * yb
    grid = LevelGrid(-200.0, -300.0, SPACING, z)
    ys = grid.y_of(np.arange(30, 170))
    xs = -ys * math.tan(lean)  # the spine leans with the trunk
    line = SymmetryLine(x=xs, y=ys, z=grid.depth(xs, ys), asymmetry=0 * ys, raw_x=xs)
    vp = np.array([xs[0], ys[0], line.z[0]])
    dm = np.array([xs[-1], ys[-1], line.z[-1]])
    normals = line_normals(grid, line, vp, dm)
    expected = -math.degrees(math.atan(0.3 * math.sin(lean)))  # z_x = 0.3·sin(lean)
    np.testing.assert_allclose(surface_rotation(normals), expected, atol=0.05)
    np.testing.assert_allclose(axial_rotation(normals, vp, dm), 0.0, atol=0.05)
    mid = spinal_midline(line, normals, vp, dm)
    np.testing.assert_allclose(mid.lateral_deviation, 0.0, atol=0.1)


def test_body_depth_model() -> None:
    np.testing.assert_allclose(body_depth(np.array([0.0, 1.0]), 440.0), [45.0, 70.0])
    np.testing.assert_allclose(body_depth(np.array([0.5]), 220.0), [28.75])


@pytest.mark.parametrize("name", ["moderate", "severe"])
def test_rotation_and_deviation_against_the_truth(name: str) -> None:
    surface, truth = back(name)
    shape = analyse_back(surface, GRAVITY)
    spine = truth["spine"]
    line = shape.symmetry_line
    true_rotation = np.interp(line[:, 1], spine["skin"][:, 1], spine["surface_rotation_deg"])
    assert np.sqrt(np.mean((shape.surface_rotation - true_rotation) ** 2)) <= 1.5
    params = shape.parameter_table()
    true_dev = np.interp(shape.midline[:, 1], spine["body"][:, 1], spine["lateral_deviation_mm"])
    vp, dm = shape.landmark("VP"), shape.landmark("DM")
    line_x = vp[0] + (dm[0] - vp[0]) * (shape.midline[:, 1] - vp[1]) / (dm[1] - vp[1])
    deviation = shape.midline[:, 0] - line_x
    assert np.sqrt(np.mean((deviation - true_dev) ** 2)) <= 2.0
    truth_max = truth["parameters"]["lateral_deviation_max_mm"]["value"]
    assert params["lateral_deviation_max_mm"]["value"] == pytest.approx(truth_max, abs=2.0)


def test_a_symmetric_back_has_no_deviation_or_rotation() -> None:
    surface, _ = back("normal")
    shape = analyse_back(surface, GRAVITY)
    params = shape.parameter_table()
    # both sides' extremes are small, and too close for the signed maxima to be reported
    for name in ("lateral_deviation", "surface_rotation"):
        unit = "mm" if name == "lateral_deviation" else "deg"
        assert params[f"{name}_pos_max_{unit}"]["value"] <= 1.0
        assert params[f"{name}_neg_max_{unit}"]["value"] >= -1.0
        assert f"{name}_max_{unit}" not in params
        assert "not decided" in shape.reason_table()[f"{name}_max_{unit}"]


def test_mirrored_back_flips_rotation_and_deviation() -> None:
    surface, _ = back("severe")
    p = analyse_back(surface, GRAVITY).parameter_table()
    m = analyse_back(mirrored(surface), GRAVITY).parameter_table()
    assert p["surface_rotation_max_deg"]["value"] > 5.0
    for name in ("surface_rotation_max_deg", "lateral_deviation_max_mm", "trunk_imbalance_mm"):
        assert m[name]["value"] == pytest.approx(-p[name]["value"], abs=0.3)
    for name in ("surface_rotation_rms_deg", "lateral_deviation_rms_mm", "scoliosis_angle_deg"):
        assert m[name]["value"] == pytest.approx(p[name]["value"], abs=0.3)


def test_a_hole_beside_the_furrow_refuses_those_levels_not_bridges_them() -> None:
    grid = _rotated_back(8.0)
    line = _straight_line(grid)
    vp = np.array([0.0, line.y[0], line.z[0]])
    dm = np.array([0.0, line.y[-1], line.z[-1]])
    # 30 mm of one side, 6 to 36 mm beside the line, missing over 60 mm of height
    z = grid.z.copy()
    ys, xs = grid.y_of(np.arange(z.shape[0])), grid.x_of(np.arange(z.shape[1]))
    z[np.ix_(np.abs(ys - line.y[80]) < 30.0, (xs > 6.0) & (xs < 36.0))] = np.nan
    holed = LevelGrid(grid.x0, grid.y0, grid.spacing, z)
    normals = line_normals(holed, line, vp, dm)
    mid = spinal_midline(line, normals, vp, dm)
    refused = ~np.isfinite(mid.rotation)
    near = np.abs(line.y - line.y[80]) < 25.0
    assert refused[near].all()
    assert not refused[np.abs(line.y - line.y[80]) > 60.0].any()
    # every array but the depth is refused at the same levels; the rest is as without the hole
    for values in (mid.points[:, 0], mid.lateral_deviation, mid.axial_rotation):
        assert np.array_equal(~np.isfinite(values), refused)
    assert np.isfinite(mid.depth).all()
    full = spinal_midline(line, line_normals(grid, line, vp, dm), vp, dm)
    far = np.abs(line.y - line.y[80]) > 60.0
    np.testing.assert_allclose(mid.rotation[far], full.rotation[far], atol=1e-9)
    # without the support check the fit extrapolates the missing side there
    loose = surface_rotation(line_normals(holed, line, vp, dm, min_support=0.0))
    assert np.isfinite(loose[near]).all()
    assert np.abs(loose[near] - full.rotation[near]).max() > 0.5
