"""Stage 6, ``surface.linear-grid``: smoothing along lines, gridding, accuracy, degenerate input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from rasterserver_plugins.smoothing import LinearGridSurface, grid_from_lines, smooth_along_lines

from rasterserver.errors import InputError
from rasterserver.records_surface import Points, Surface
from rasterserver.registry import Registry
from rasterserver.stage import StageContext, run_stage


def _points(x, y, z, number, col, *, row=None, area=None) -> Points:
    n = len(x)
    return Points(
        x=np.asarray(x, dtype=np.float64),
        y=np.asarray(y, dtype=np.float64),
        z=np.asarray(z, dtype=np.float64),
        number=np.asarray(number, dtype=np.int32),
        col=np.asarray(col, dtype=np.int32),
        row=np.zeros(n) if row is None else np.asarray(row, dtype=np.float64),
        area=np.ones(n, np.float32) if area is None else np.asarray(area, dtype=np.float32),
        image_shape=np.array([604, 576]),
    )


def _synthetic_lines(
    surface, *, lines: range = range(10, 40), cols: range = range(100, 400), noise: float = 0.0
) -> Points:
    """Raster-like points: line k at y ≈ 10 (k - 25) mm, one peak per column 1 mm apart."""
    number, col = np.meshgrid(np.array(lines), np.array(cols), indexing="ij")
    x = (col - 250.0).astype(np.float64)
    y = 10.0 * (number - 25) + 0.02 * x  # lines are slightly slanted, as on a real back
    z = surface(x, y)
    if noise:
        z = z + np.random.default_rng(0).normal(0.0, noise, z.shape)
    return _points(x.ravel(), y.ravel(), z.ravel(), number.ravel(), col.ravel())


def _run(points: Points, **params) -> Surface:
    return run_stage(LinearGridSurface, points, params, StageContext())


def test_found_through_the_entry_point() -> None:
    assert isinstance(Registry().discover().get("surface.linear-grid"), LinearGridSurface)


def test_block_means_of_three_peaks_reduce_to_a_third() -> None:
    rng = np.random.default_rng(1)
    n = 12
    x = np.arange(n, dtype=float)
    z = rng.normal(size=n)
    pts = _points(x, 2 * x, z, np.full(n, 5), np.arange(50, 50 + n), row=x + 0.5, area=x)
    out = smooth_along_lines(pts, window=3, step=3)
    assert len(out) == 4
    np.testing.assert_allclose(out.z, z.reshape(4, 3).mean(axis=1))
    np.testing.assert_allclose(out.x, [1, 4, 7, 10])
    np.testing.assert_array_equal(out.col, [51, 54, 57, 60])
    np.testing.assert_allclose(out.row, [1.5, 4.5, 7.5, 10.5])
    np.testing.assert_allclose(out.area, [1, 4, 7, 10])
    # a moving average without decimation keeps every peak with two neighbours
    assert len(smooth_along_lines(pts, window=3, step=1)) == n - 2


def test_end_blocks_leave_no_runs_end_without_a_point() -> None:
    # one line over columns 0-10: a run of 11 peaks gives blocks centred at 1, 4 and 7, and
    # columns 9-10 make no point; the end block adds one centred at 9 (over 8-10)
    n = 11
    x = np.arange(n, dtype=float)
    pts = _points(x, np.zeros(n), 0.1 * x**2, np.full(n, 3), np.arange(n))
    np.testing.assert_array_equal(smooth_along_lines(pts).col, [1, 4, 7])
    ends = smooth_along_lines(pts, end_blocks=True)
    np.testing.assert_array_equal(ends.col, [1, 4, 7, 9])
    np.testing.assert_allclose(ends.z[-1], np.mean(0.1 * x[8:11] ** 2))
    # a run whose steps end on its last peak needs none; a run shorter than the window none
    assert smooth_along_lines(pts.take(np.arange(9)), end_blocks=True).col.tolist() == [1, 4, 7]
    assert len(smooth_along_lines(pts.take(np.arange(2)), end_blocks=True)) == 0
    # a gap of one column filled (tuning body 10's line 28: runs 0-6 and 8-10 joined) no
    # longer moves the last point away from the line's end
    split = pts.take(np.flatnonzero(np.arange(n) != 7))
    assert smooth_along_lines(split).col.max() == 9
    assert smooth_along_lines(pts).col.max() == 7
    assert smooth_along_lines(pts, end_blocks=True).col.max() == 9


def test_the_stage_makes_no_end_blocks() -> None:
    # measured and not adopted (BENCHMARKS.md "Real bodies", 2026-11-30 (32)): version 1
    assert LinearGridSurface.version == "1"
    assert "end_blocks" not in LinearGridSurface.Params.model_fields


def test_runs_break_at_gaps_numbers_and_depth_jumps() -> None:
    # line 1: columns 0-3, then 5-8 with an arm in front from column 7; line 2: columns 9-13
    col = np.array([0, 1, 2, 3, 5, 6, 7, 8, 9, 10, 11, 12, 13])
    number = np.array([1] * 8 + [2] * 5)
    z = np.where((number == 1) & (col >= 7), 30.0, 0.0)
    pts = _points(col.astype(float), np.zeros(col.size), z, number, col)
    out = smooth_along_lines(pts, window=3, step=3)
    # runs of >= 3: columns 0-3 of line 1 (one sample), 9-13 of line 2 (one sample)
    np.testing.assert_array_equal(out.col, [1, 10])
    np.testing.assert_array_equal(out.number, [1, 2])
    assert np.all(out.z == 0.0)


def test_input_order_does_not_matter() -> None:
    pts = _synthetic_lines(lambda x, y: 0.001 * x * y)
    shuffled = pts.take(np.random.default_rng(2).permutation(len(pts)))
    a, b = _run(pts), _run(shuffled)
    np.testing.assert_array_equal(a.z, b.z)
    np.testing.assert_array_equal(a.samples, b.samples)


@pytest.mark.parametrize("cubic", [True, False])
def test_planes_are_reproduced_exactly(cubic: bool) -> None:
    def plane(x, y):
        return 5.0 + 0.3 * x - 0.2 * y

    surface = _run(_synthetic_lines(plane), cubic=cubic)
    xs, ys = surface.coordinates()
    gx, gy = np.meshgrid(xs, ys)
    valid = surface.valid
    assert valid.sum() > 0.8 * valid.size
    np.testing.assert_allclose(surface.z[valid], plane(gx, gy)[valid], atol=1e-9)


def test_cubic_interpolation_is_exact_for_parabolas_across_lines() -> None:
    def bowl(x, y):
        return 0.002 * y**2

    surface = _run(_synthetic_lines(bowl), cubic=True)
    xs, ys = surface.coordinates()
    gx, gy = np.meshgrid(xs, ys)
    err = np.abs(surface.z - bowl(gx, gy))[surface.valid]
    # 5e-7: the block mean of three peaks on the slightly curved line; linear would sag by
    # curvature x 10² / 8 = 0.05 mm
    assert err.max() < 1e-6
    linear = _run(_synthetic_lines(bowl), cubic=False)
    assert np.nanmax(np.abs(linear.z - bowl(gx, gy))) > 0.04


def test_grid_origin_lies_on_multiples_of_the_spacing() -> None:
    surface = _run(_synthetic_lines(lambda x, y: 0 * x), spacing=2.5)
    assert surface.spacing == 2.5
    assert surface.x0 / 2.5 == pytest.approx(round(surface.x0 / 2.5))
    assert surface.y0 / 2.5 == pytest.approx(round(surface.y0 / 2.5))


def test_missing_lines_and_line_gaps_stay_holes() -> None:
    pts = _synthetic_lines(lambda x, y: 0 * x)
    keep = (pts.number != 20) & ~((pts.number == 30) & (pts.col >= 200) & (pts.col < 230))
    surface = _run(pts.take(keep))
    xs, ys = surface.coordinates()
    gx, gy = np.meshgrid(xs, ys)
    line_y = lambda k, x: 10.0 * (k - 25) + 0.02 * x  # noqa: E731
    # nothing between lines 19 and 21: one missing line is not bridged by default
    inner = (gx > pts.x.min() + 1) & (gx < pts.x.max() - 1)
    between = inner & (gy > line_y(19, gx) + 0.5) & (gy < line_y(21, gx) - 0.5)
    assert between.any() and not surface.valid[between].any()
    # the 30 mm gap in line 30 leaves cells on either side of it unfilled
    gap = (gx > -45) & (gx < -25) & (np.abs(gy - line_y(30, gx)) < 3)
    assert gap.any() and not surface.valid[gap].all()
    # bridging one missing line can be asked for
    bridged = _run(pts.take(keep), max_line_step=2)
    assert bridged.valid[between].all()


def test_noise_is_reduced_by_smoothing() -> None:
    pts = _synthetic_lines(lambda x, y: 0 * x, noise=0.3)
    surface = _run(pts)
    assert len(surface.samples) == pytest.approx(len(pts) / 3, rel=0.02)
    sample_rms = np.sqrt(np.mean(surface.samples[:, 2] ** 2))
    assert sample_rms == pytest.approx(0.3 / np.sqrt(3), rel=0.1)
    grid_rms = np.sqrt(np.nanmean(surface.z**2))
    assert grid_rms < sample_rms
    smoothed = _run(pts, sigma=4.0)
    assert np.sqrt(np.nanmean(smoothed.z**2)) < 0.5 * grid_rms


def test_delaunay_method_and_its_distance_mask() -> None:
    pts = _synthetic_lines(lambda x, y: 0.1 * x)
    keep = ~((pts.col > 200) & (pts.col < 260))
    surface = _run(pts.take(keep), method="delaunay", max_gap=8.0)
    xs, ys = surface.coordinates()
    gx, _ = np.meshgrid(xs, ys)
    assert not surface.valid[(gx > -35) & (gx < -5)].any()
    np.testing.assert_allclose(surface.z[surface.valid], 0.1 * gx[surface.valid], atol=1e-9)


def test_counts_and_samples_describe_the_grid() -> None:
    pts = _synthetic_lines(lambda x, y: 0 * x)
    surface = _run(pts)
    assert surface.count is not None and surface.count.shape == surface.z.shape
    assert surface.count.sum() == len(surface.samples)
    back = surface.sample_points()
    assert back is not None and len(back) == len(surface.samples)
    np.testing.assert_array_equal(back.number, surface.sample_number)
    without = _run(pts, keep_samples=False)
    assert without.samples is None and without.sample_points() is None
    np.testing.assert_array_equal(without.z, surface.z)


def test_empty_and_tiny_input_give_an_empty_surface_with_a_reason() -> None:
    empty = Points.empty((604, 576), "no numbered raster lines")
    surface = _run(empty)
    assert surface.z.shape == (0, 0)
    assert "no points" in surface.reason and "no numbered raster lines" in surface.reason
    two = _points([0.0, 1.0], [0.0, 0.0], [0.0, 0.0], [3, 3], [10, 11])
    assert "smoothed points" in _run(two).reason


def test_a_single_line_has_no_surface_between_lines() -> None:
    pts = _synthetic_lines(lambda x, y: 0 * x, lines=range(20, 21))
    surface = _run(pts)
    assert not surface.valid.any()
    assert "between two neighbouring lines" in surface.reason


def test_invalid_parameters_are_refused() -> None:
    pts = _synthetic_lines(lambda x, y: 0 * x)
    with pytest.raises(InputError, match="odd"):
        _run(pts, window=4)
    with pytest.raises(InputError, match="spacing"):
        _run(pts, spacing=0.0)
    with pytest.raises(InputError, match="unknown parameter"):
        _run(pts, smoothness=3)


def test_grid_from_lines_direct_call() -> None:
    pts = _synthetic_lines(lambda x, y: 1.0 + 0 * x)
    x0, y0, z = grid_from_lines(pts, spacing=5.0, max_gap=3.0)
    assert np.nanmin(z) == np.nanmax(z) == 1.0
    assert x0 <= pts.x.min() < x0 + 5.0 and y0 <= pts.y.min() < y0 + 5.0


def test_surface_record_validation() -> None:
    surface = _run(_synthetic_lines(lambda x, y: 0 * x))
    assert Surface.from_arrays(surface.to_arrays()) == surface
    with pytest.raises(InputError, match="spacing"):
        dataclasses.replace(surface, spacing=-1.0)
    with pytest.raises(InputError, match="count"):
        dataclasses.replace(surface, count=surface.count[1:])


@pytest.mark.parametrize("name", ["plane", "sphere", "back"])
def test_smoothed_accuracy_on_rendered_scenes(name: str) -> None:
    """The seed's figures: ≈ 0.5 mm raw, 0.2 mm after smoothing (rms distance to the truth)."""
    pytest.importorskip("rasterserver.records_lines")
    import geometry_truth as gt
    from rasterserver_plugins.reconstruction import RayPlaneReconstruction

    station = gt.station()
    context = StageContext(calibration=station, raster=station.raster_definition)
    rendering = gt.rendering(name)
    # 0.1 px rows noise: twice the seed's peak accuracy
    lines = gt.numbered_lines(rendering.line_rows, rendering.image.shape, noise=0.1, seed=4)
    points = run_stage(RayPlaneReconstruction, lines, None, context)
    surface = run_stage(LinearGridSurface, points, None, context)
    raw = gt.rms(gt.distance_to_scene(gt.scene(name), points.xyz))
    smoothed = gt.rms(gt.distance_to_scene(gt.scene(name), surface.samples))
    grid = gt.rms(gt.distance_to_scene(gt.scene(name), surface.grid_points()))
    assert raw <= 0.5
    assert smoothed <= 0.2 and smoothed < 0.7 * raw
    assert grid <= 0.2
    # ≈ 25,000 peaks → ≈ 8,000 points on the back, as in the seed
    assert len(surface.samples) == pytest.approx(len(points) / 3, rel=0.05)
    assert surface.valid.sum() > 0.9 * len(surface.samples)
