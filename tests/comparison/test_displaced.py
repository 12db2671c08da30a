"""Regions of a distance map where the visits' arms lie otherwise: found on synthetic maps
(an arm's step at the outline; a changed back inside, or reaching the outline gently, left
alone) and on two simulated visits of one person holding the arms otherwise."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from rasterserver.comparison import (
    THRESHOLDS,
    DistanceMap,
    Registration,
    Visit,
    displaced_regions,
    distance_map,
    register,
)
from rasterserver.comparison.displaced import distance_slope, mesh_boundary


def grid(width: float = 300.0, height: float = 240.0, step: float = 4.0):
    """A flat trunk-sized mesh: vertices (N, 3) and triangles."""
    xs = np.arange(-width / 2, width / 2 + 1e-9, step)
    ys = np.arange(0.0, height + 1e-9, step)
    gx, gy = np.meshgrid(xs, ys)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    nx = len(xs)
    i, j = np.meshgrid(np.arange(len(ys) - 1), np.arange(nx - 1), indexing="ij")
    k = (i * nx + j).ravel()
    triangles = np.vstack(
        [np.column_stack([k, k + 1, k + nx]), np.column_stack([k + 1, k + nx + 1, k + nx])]
    ).astype(np.int32)
    return vertices, triangles


def find(vertices: np.ndarray, triangles: np.ndarray, distance: np.ndarray) -> np.ndarray:
    return displaced_regions(
        vertices,
        triangles,
        distance,
        limit=THRESHOLDS.displaced_limit or 15.0,
        slope=THRESHOLDS.displaced_slope,
        margin=THRESHOLDS.displaced_margin,
    )


def noise(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, 0.05, n)


def test_an_arm_at_the_outline_is_not_compared_and_the_back_is() -> None:
    v, t = grid()
    x = v[:, 0]
    # the arm: 20-25 mm in front of the other visit's flank beyond x = 120, ramping up over
    # 15 mm; beyond x = 140 the other visit has no surface within reach
    d = noise(len(v)) - np.clip((x - 105.0) / 15.0, 0.0, 1.0) * 22.0
    d[x > 140.0] = np.nan
    out = find(v, t, d)
    assert out[x >= 105.0].all()  # the arm and its ramp
    assert out[(x > 85.0) & (x < 105.0)].all()  # the margin
    assert not out[x < 80.0].any()  # the back
    assert np.sqrt(np.nanmean(np.where(out, np.nan, d) ** 2)) < 0.1


def test_a_changed_back_is_compared() -> None:
    v, t = grid()
    x, y = v[:, 0], v[:, 1]
    # a rib hump grown by 14 mm inside the trunk (beyond the limit would it reach the
    # outline: it does not)
    hump = 14.0 * np.exp(-((x - 60.0) ** 2 + (y - 120.0) ** 2) / (2 * 30.0**2))
    assert not find(v, t, hump + noise(len(v))).any()
    # the flank turned back by 12 mm at the outline, gently: below the limit
    flank = -12.0 * np.clip((x - 30.0) / 120.0, 0.0, 1.0)
    assert not find(v, t, flank + noise(len(v))).any()
    # beyond the limit but gently (0.1 mm per mm): a region reaching the outline is found,
    # but not the gentle slope leading to it
    steep_free = -20.0 * np.clip((x - 0.0) / 150.0, 0.0, 1.0)
    out = find(v, t, steep_free)
    assert out.any() and not out[x < 90.0].any()


def test_what_is_only_unmeasured_or_inside_is_left_to_the_map() -> None:
    v, t = grid()
    x, y = v[:, 0], v[:, 1]
    d = noise(len(v))
    d[x > 130.0] = np.nan  # the other visit does not reach so far: no value, nothing found
    assert not find(v, t, d).any()
    d = noise(len(v))
    d[(np.abs(x) < 20.0) & (np.abs(y - 120.0) < 20.0)] = 25.0  # an island inside
    assert not find(v, t, d).any()


def test_degenerate_maps() -> None:
    empty = np.zeros((0, 3))
    none = np.zeros((0, 3), dtype=np.int32)
    assert find(empty, none, np.zeros(0)).shape == (0,)
    v, t = grid(40.0, 40.0)
    assert not find(v, t, np.zeros(len(v))).any()
    assert not find(v, none, np.full(len(v), 25.0)).any()  # no boundary without triangles
    assert mesh_boundary(none, 3).tolist() == [False, False, False]


def test_slope_of_a_linear_distance() -> None:
    v, t = grid(100.0, 100.0)
    np.testing.assert_allclose(distance_slope(v, t, 0.3 * v[:, 0] - 0.4 * v[:, 1]), 0.5)
    d = np.zeros(len(v))
    d[0] = np.nan
    slope = distance_slope(v, t, d)
    assert np.isinf(slope[0]) and slope[-1] == 0.0


def test_statistics_count_the_displaced_area() -> None:
    v, t = grid(100.0, 100.0)
    displaced = v[:, 0] > 25.0
    d = np.where(displaced, np.nan, 0.1)
    stats = DistanceMap(v, t, v * 0 + [0, 0, 1], d, displaced=displaced).statistics()
    assert 0.2 < stats["displaced"] < 0.3
    assert stats["displaced"] + stats["overlap"] == pytest.approx(1.0)
    assert DistanceMap(v, t, v * 0 + [0, 0, 1], np.zeros(len(v))).statistics()["displaced"] == 0


def _visits(seed: int) -> tuple[Visit, Visit]:
    """One person seen twice by a clinic station, the arms held otherwise the second time."""
    from rasterserver.pipeline import run_chain
    from rasterserver.simulator.back import posture_sway
    from rasterserver.simulator.body import clinic_station, make_body, random_body
    from rasterserver.simulator.render import RenderSettings, render
    from rasterserver.stage import StageContext

    body = random_body(seed)  # tuning scenes of benchmarks/clinic_comparison.py
    station = clinic_station(seed)
    context = StageContext(calibration=station, raster=station.raster_definition)
    other = dataclasses.replace(
        body,
        arm_posture="hips" if body.arm_posture != "hips" else "away",
        back=posture_sway(body.back, 3, translation=5.0, rotation=1.0),
    )
    visits = []
    for k, params in enumerate((body, other)):
        image = render(make_body(params), station, settings=RenderSettings(supersampling=1), seed=k)
        records = run_chain(image.image, context=context, until="analysis")
        mesh = run_chain(records["surface"], context=context, until="mesh")["mesh"]
        visits.append(Visit(records["surface"], mesh, records["analysis"], label=f"v{k}"))
        assert not records["analysis"].reason
    return visits[0], visits[1]


VERSION_1 = dataclasses.replace(THRESHOLDS, displaced_limit=None, axis_window=None)


def _map(a: Visit, b: Visit, thresholds: object) -> dict:
    reg = register(a, b, thresholds=thresholds)  # type: ignore[arg-type]
    assert isinstance(reg, Registration)
    return distance_map(a, b, reg, thresholds=thresholds).statistics()  # type: ignore[arg-type]


@pytest.mark.parametrize("seed", [45, 38])
def test_arms_held_otherwise_do_not_show_as_a_change(seed: int) -> None:
    a, b = _visits(seed)
    before, after = _map(a, b, VERSION_1), _map(a, b, THRESHOLDS)
    # version 1 shows the arms as a change of centimetres on an unchanged back
    assert before["rms_mm"] > 1.0 and abs(before["max_abs_mm"]) > 15.0
    assert after["rms_mm"] < 0.2 and abs(after["max_abs_mm"]) < 5.0
    # each of the two steps alone: the arms apart from the trunk in a row, and the regions
    # where an arm touches it
    rows = _map(a, b, dataclasses.replace(THRESHOLDS, displaced_limit=None))
    regions = _map(a, b, dataclasses.replace(THRESHOLDS, axis_window=None))
    assert rows["vertices"] < before["vertices"] == regions["vertices"]
    assert regions["displaced"] > 0.02 and regions["rms_mm"] < 0.5
