"""Clinical parameters: their building blocks on exact lines, and all of them against the truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from back_surfaces import GRAVITY, back
from rasterserver_plugins.back_parameters import (
    PARAMETER_UNITS,
    SIGN_MARGIN,
    asymmetry_rms,
    cobb_angle,
    signed_extremes,
    undecided_sign,
)
from rasterserver_plugins.back_shape import analyse_back
from rasterserver_plugins.level_frame import LevelGrid
from rasterserver_plugins.trunk import find_trunk


def test_signed_extremes() -> None:
    rms, signed, high, low = signed_extremes(np.array([1.0, -3.0, 2.0]))
    assert rms == pytest.approx(math.sqrt(14 / 3))
    assert (signed, high, low) == (-3.0, 2.0, -3.0)
    # a curve that stays on one side: the other side's extreme is 0
    assert signed_extremes(np.array([1.0, 2.0]))[2:] == (2.0, 0.0)
    assert all(math.isnan(v) for v in signed_extremes(np.array([np.nan])))


def test_cobb_angle_of_exact_lines() -> None:
    y = np.arange(0.0, 450.0, 3.0)
    assert cobb_angle(y, np.full_like(y, 7.0), 3.0) == pytest.approx(0.0, abs=1e-9)
    # one C curve: the tangents at its ends are ±atan(A π / H)
    amplitude, height = 30.0, 450.0
    x = amplitude * np.sin(np.pi * y / height)
    expected = 2.0 * math.degrees(math.atan(amplitude * math.pi / height))
    assert cobb_angle(y, x, 3.0) == pytest.approx(expected, abs=0.5)
    # an S: two curves, the larger one counts
    s = 25.0 * np.sin(2 * np.pi * y / height)
    inner = 2.0 * math.degrees(math.atan(25.0 * 2 * np.pi / height))
    assert cobb_angle(y, s, 3.0) == pytest.approx(inner, abs=1.0)


def test_cobb_angle_reads_each_measured_piece_of_a_line_with_gaps() -> None:
    y = np.arange(0.0, 450.0, 3.0)
    s = 25.0 * np.sin(2 * np.pi * y / 450.0)
    inner = 2.0 * math.degrees(math.atan(25.0 * 2 * np.pi / 450.0))
    # a gap away from the curves' end vertebrae (the tangents' extremes) changes nothing
    gap = s.copy()
    gap[(y > 60.0) & (y < 90.0)] = np.nan
    assert cobb_angle(y, gap, 3.0) == pytest.approx(cobb_angle(y, s, 3.0), abs=0.3)
    assert cobb_angle(y, gap, 3.0) == pytest.approx(inner, abs=1.0)
    # a gap's edges are no extremes: a straight line with holes stays straight
    flat = np.where((y > 200.0) & (y < 230.0), np.nan, 7.0)
    assert cobb_angle(y, flat, 3.0) == pytest.approx(0.0, abs=1e-9)
    # nothing long enough for a centred tangent: no angle
    bits = np.where((y // 30.0) % 2 == 0, s, np.nan)
    assert math.isnan(cobb_angle(y, bits, 3.0))
    assert math.isnan(cobb_angle(y, np.full_like(y, np.nan), 3.0))
    # a lone measured sample, or a line of one sample: no tangent, no angle (no crash)
    lone = np.full_like(y, np.nan)
    lone[40] = 1.0
    assert math.isnan(cobb_angle(y, lone, 3.0))
    assert math.isnan(cobb_angle(y[:1], s[:1], 3.0))


def test_asymmetry_of_a_symmetric_and_a_lopsided_back() -> None:
    y, x = np.mgrid[-300:300:3.0, -200:200:3.0]
    z = np.where(np.abs(x) < 150, 40.0 + (x / 30.0) ** 2, np.nan)
    grid = LevelGrid(-200.0, -300.0, 3.0, z)
    trunk = find_trunk(z, 3.0)
    vp, dm = np.array([0.0, -250.0, 40.0]), np.array([0.0, 250.0, 40.0])
    right = np.array([1.0, 0.0, 0.0])
    # (bilinear interpolation of the mirrored parabola between cells: a few µm)
    assert asymmetry_rms(grid, trunk, vp, dm, right) == pytest.approx(0.0, abs=0.01)
    hump = z - 8.0 * np.exp(-0.5 * (((x - 60) / 25) ** 2 + (y / 80) ** 2))
    lopsided = LevelGrid(-200.0, -300.0, 3.0, hump)
    assert asymmetry_rms(lopsided, find_trunk(hump, 3.0), vp, dm, right) > 0.5


#: Largest error of each parameter against the truth on the preset backs.
TOLERANCE = {
    "trunk_length": 3.0,
    "trunk_inclination_mm": 2.0,
    "trunk_inclination_deg": 0.5,
    "trunk_imbalance_mm": 1.5,
    "trunk_imbalance_deg": 0.3,
    "pelvic_tilt_mm": 2.0,
    "pelvic_tilt_deg": 1.0,
    "pelvic_torsion_deg": 3.0,
    "pelvic_rotation_deg": 1.0,
    "kyphotic_angle_deg": 4.0,
    "lordotic_angle_deg": 4.0,
    "fleche_cervicale_mm": 2.0,
    "fleche_lombaire_mm": 2.0,
    "surface_rotation_rms_deg": 0.5,
    "surface_rotation_max_deg": 1.0,
    "surface_rotation_pos_max_deg": 1.0,
    "surface_rotation_neg_max_deg": 1.0,
    "lateral_deviation_rms_mm": 1.0,
    "lateral_deviation_max_mm": 2.0,
    "lateral_deviation_pos_max_mm": 2.0,
    "lateral_deviation_neg_max_mm": 2.0,
    "scoliosis_angle_deg": 4.0,
}


@pytest.mark.parametrize("name", ["normal", "moderate", "severe"])
def test_parameters_against_the_truth(name: str) -> None:
    surface, truth = back(name)
    shape = analyse_back(surface, GRAVITY)
    params = shape.parameter_table()
    # a straight back deviates and turns as little to one side as to the other: the sign of
    # its largest deviation and rotation is noise, and refused
    refused = set(PARAMETER_UNITS) - set(params)
    expected = set(SIGN_MARGIN) if name == "normal" else set()
    assert refused == expected, shape.reason_table()
    for key in refused:
        assert "not decided by the measurement" in shape.reason_table()[key]
    for key, entry in params.items():
        assert entry["unit"] == PARAMETER_UNITS[key] and entry["spread"] is None
    for key, limit in TOLERANCE.items():
        if key in refused:
            continue
        value, true = params[key]["value"], truth["parameters"][key]["value"]
        assert abs(value - true) <= limit, f"{name} {key}: {value:.2f}, truth {true:.2f}"
    assert 0.0 <= params["asymmetry_rms_mm"]["value"] < 20.0
    # the sagittal profile's points, in height order, on the symmetry line
    points = [shape.sagittal_point(k) for k in ("ICT", "KA", "ITL", "LA", "ILS")]
    heights = [p[1] for p in points]
    assert heights == sorted(heights)
    for key in ("KA", "ITL", "LA"):
        assert np.linalg.norm(shape.sagittal_point(key) - truth["landmarks"][key]) < 25.0


@pytest.mark.parametrize(
    ("pos", "neg", "refused"),
    [
        (18.4, -18.2, True),  # a double curve of two equal sides
        (17.4, -17.9, True),
        (0.2, -0.2, True),  # a straight back
        (18.0, -5.0, False),
        (1.6, 0.0, False),  # one side only, clear of the margin
        (0.0, -1.4, True),
        (math.nan, math.nan, False),  # nothing measured: missing for another reason
    ],
)
def test_undecided_sign(pos: float, neg: float, refused: bool) -> None:
    peak = pos if abs(pos) >= abs(neg) else neg
    why = undecided_sign((1.0, peak, pos, neg), 1.5, "mm")
    assert bool(why) is refused
    if refused:
        assert f"{pos:+.1f} and {neg:+.1f} mm" in why and "within 1.5 mm" in why
