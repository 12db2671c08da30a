"""Peak detection against exact line centres: synthetic lines and simulated backs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from image_truth import back, synthetic_lines, truth_of_peaks, wall
from rasterserver_plugins.peak_detection import VERSION_5, FirstMomentPeaks, detect_peaks

from rasterserver.records import Image
from rasterserver.records_lines import Peaks
from rasterserver.stage import run_stage


def _run(pixels: np.ndarray, **params: object) -> Peaks:
    return run_stage(FirstMomentPeaks, Image(pixels), params)


def _match(peaks: Peaks, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Row error of the peak nearest to each exact centre in its column."""
    errors = np.full(rows.size, np.inf)
    for c in np.unique(cols):
        found = peaks.row[peaks.col == c]
        if found.size:
            exact = rows[cols == c]
            d = found[None, :] - exact[:, None]
            errors[cols == c] = d[np.arange(exact.size), np.abs(d).argmin(axis=1)]
    return errors


def test_synthetic_lines_noise_free() -> None:
    image, cols, rows = synthetic_lines(sigma=1.0, tilt=0.05)
    peaks = _run(image)
    assert peaks.n_peaks == rows.size
    err = _match(peaks, cols, rows)
    # only 8-bit rounding: far below the seed's 0.05 px
    assert np.sqrt(np.mean(err**2)) < 0.02
    assert np.all(peaks.area > 0) and np.all(peaks.height > 0)
    assert np.all(peaks.width >= 3)


def test_synthetic_lines_with_noise() -> None:
    image, cols, rows = synthetic_lines(sigma=1.2, noise=1.5, seed=4)
    peaks = _run(image)
    err = _match(peaks, cols, rows)
    assert np.mean(np.abs(err) < 0.5) > 0.99
    assert np.sqrt(np.mean(err[np.abs(err) < 0.5] ** 2)) < 0.05


def test_area_tells_heavy_from_light() -> None:
    light, _cols, _rows = synthetic_lines(sigma=1.0, amplitude=80.0)
    heavy, _, _ = synthetic_lines(sigma=1.5, amplitude=80.0)
    a_light = np.median(_run(light).area)
    a_heavy = np.median(_run(heavy).area)
    assert 1.3 < a_heavy / a_light < 1.8


def test_saturated_lines_keep_their_centre() -> None:
    # judged without the trust test, which drops clipped tops (next test)
    image, cols, rows = synthetic_lines(sigma=1.5, amplitude=600.0)
    assert (image == 255).sum() > 100
    peaks = _run(image, trust=False)
    err = _match(peaks, cols, rows)
    assert np.sqrt(np.mean(err**2)) < 0.1
    assert peaks.dropped == 0


def test_clipped_peaks_are_dropped_and_counted() -> None:
    image, _cols, rows = synthetic_lines(sigma=1.5, amplitude=600.0)
    every = _run(image, trust=False)
    trusted = _run(image)
    assert trusted.n_peaks + trusted.dropped == every.n_peaks
    assert trusted.dropped >= rows.size // 2
    # lines below the ceiling lose nothing
    clean, _, clean_rows = synthetic_lines(sigma=1.5, amplitude=120.0)
    assert _run(clean).dropped == 0 and _run(clean).n_peaks == clean_rows.size


def test_dim_and_asymmetric_peaks_are_dropped_and_counted() -> None:
    # dim lines under noise: the trusted peaks are more accurate than all of them
    image, cols, rows = synthetic_lines(sigma=1.2, amplitude=9.0, background=20.0, noise=1.5)
    every = _run(image, trust=False)
    trusted = _run(image, min_trust_height=6.0)
    assert trusted.dropped > 0 and trusted.n_peaks + trusted.dropped == every.n_peaks

    def rms(peaks: Peaks) -> float:
        err = _match(peaks, cols, rows)
        return float(np.sqrt(np.mean(err[np.abs(err) < 1.0] ** 2)))

    assert rms(trusted) < rms(every)


def test_overlapping_neighbour_is_dropped() -> None:
    # an overlapping neighbour: one flank's bounding minimum is high, the peak is dropped
    col = np.arange(40, dtype=np.float64)
    y = np.arange(60, dtype=np.float64)[:, None]
    pair = (
        10
        + 100 * np.exp(-0.5 * ((y - 30) / 1.2) ** 2)
        + 60 * np.exp(-0.5 * ((y - 34.5) / 1.2) ** 2)
    )
    img = np.clip(np.repeat(pair, col.size, axis=1), 0, 255).astype(np.uint8)
    assert _run(img, trust=False).n_peaks == 2 * col.size
    kept = _run(img)
    assert kept.dropped >= col.size and kept.n_peaks + kept.dropped == 2 * col.size


def test_simulated_back_accuracy_and_count() -> None:
    r = back("normal", supersampling=3)
    peaks = _run(r.image)
    assert peaks.n_peaks > 20_000  # the seed: ~25,000 for a medium-sized subject
    number, exact = truth_of_peaks(peaks.col, peaks.row, r.line_rows)
    matched = number >= 0
    # nearly every detected peak is a line centre, nearly every line centre is detected
    assert matched.mean() > 0.995
    assert matched.sum() > 0.97 * len(r.line_rows)
    err = peaks.row[matched] - exact[matched]
    assert np.sqrt(np.mean(err**2)) < 0.05  # the seed's figure
    assert abs(np.mean(err)) < 0.01


def test_flat_wall() -> None:
    r = wall()
    peaks = _run(r.image)
    number, exact = truth_of_peaks(peaks.col, peaks.row, r.line_rows)
    assert (number >= 0).mean() > 0.99
    assert peaks.n_peaks > 0.97 * len(r.line_rows)
    err = peaks.row[number >= 0] - exact[number >= 0]
    assert np.sqrt(np.mean(err**2)) < 0.06


def test_output_is_sorted_and_typed() -> None:
    image, _, _ = synthetic_lines()
    peaks = _run(image)
    assert peaks.col.dtype == np.int32 and peaks.row.dtype == np.float64
    assert peaks.area.dtype == np.float32 and peaks.width.dtype == np.int16
    assert tuple(peaks.image_shape) == image.shape
    key = peaks.col * 1000.0 + peaks.row
    assert np.all(np.diff(key) > 0)


@pytest.mark.parametrize(
    "pixels",
    [
        np.zeros((604, 576), np.uint8),
        np.full((604, 576), 255, np.uint8),
        np.full((604, 576), 90, np.uint8),
        np.full((50, 40), 4000, np.uint16),
        np.zeros((1, 576), np.uint8),
        np.zeros((604, 1), np.uint8),
        np.zeros((2, 2), np.uint8),
        np.zeros((1, 1), np.uint8),
    ],
    ids=["black", "saturated", "uniform", "uniform-16bit", "1-row", "1-col", "2x2", "1x1"],
)
def test_degenerate_images_give_no_peaks(pixels: np.ndarray) -> None:
    peaks = _run(pixels)
    assert peaks.n_peaks == 0
    assert tuple(peaks.image_shape) == pixels.shape


@pytest.mark.parametrize("sigma", [1.0, 1.5, 2.0, 3.0, 6.0])
def test_pure_noise_gives_few_peaks(sigma: float) -> None:
    # the heights rise with the frame's noise: a noisier camera finds no more false peaks
    rng = np.random.default_rng(7)
    pixels = np.clip(rng.normal(40.0, sigma, (604, 576)), 0, 255).astype(np.uint8)
    assert _run(pixels).n_peaks < 10


# version 3's fixed heights, for comparison
_VERSION_3 = {"min_height": 5.0, "min_trust_height": 6.0, "min_slope": 2.5, "noise_factor": 0.0}


def test_noisy_frame_needed_fixed_heights_higher() -> None:
    # version 3's fixed 5 DN let a noisy camera's background through; version 4 does not
    rng = np.random.default_rng(7)
    pixels = np.clip(rng.normal(40.0, 3.0, (604, 576)), 0, 255).astype(np.uint8)
    assert _run(pixels, **_VERSION_3).n_peaks > 1000
    assert _run(pixels).n_peaks == 0


@pytest.mark.parametrize("noise", [0.0, 0.5])
def test_dim_lines_of_a_quiet_camera_are_found_and_kept(noise: float) -> None:
    # lines 8 DN high: below version 3's fixed heights, above a quiet camera's noise
    image, cols, rows = synthetic_lines(
        sigma=1.2, amplitude=8.0, background=20.0, noise=noise, seed=3
    )
    old = _run(image, **_VERSION_3)
    new = _run(image)
    assert new.n_peaks > 2 * old.n_peaks
    assert new.n_peaks >= (1.0 if noise == 0 else 0.7) * rows.size
    # every peak found is a line's (no false peak), and located to a tenth of a pixel
    truth = {c: rows[cols == c] for c in np.unique(cols)}
    off = [np.min(np.abs(truth[c] - r)) for c, r in zip(new.col, new.row, strict=True)]
    assert max(off) < 1.0
    assert np.sqrt(np.mean(np.square(off))) < (0.05 if noise == 0 else 0.15)


def test_noise_factor_zero_uses_the_heights_as_given() -> None:
    image, _cols, _rows = synthetic_lines(sigma=1.2, amplitude=8.0, background=20.0, noise=2.0)
    floor = detect_peaks(image, min_height=3.0, min_trust_height=3.0, noise_factor=0.0)
    scaled = detect_peaks(image, min_height=3.0, min_trust_height=3.0, noise_factor=3.5)
    assert floor.col.size + floor.dropped > scaled.col.size + scaled.dropped


def test_one_column_image_with_lines() -> None:
    image, _cols, rows = synthetic_lines((120, 1), tilt=0.0)
    peaks = _run(image)
    assert peaks.n_peaks == rows.size
    assert np.allclose(np.sort(peaks.row), np.sort(rows), atol=0.05)


def test_hot_pixel_is_not_a_peak() -> None:
    pixels = np.full((60, 5), 10, np.uint8)
    pixels[30, 2] = 200
    assert detect_peaks(pixels).col.size == 0


def test_sixteen_bit_input() -> None:
    image, _cols, _rows = synthetic_lines()
    peaks8 = _run(image)
    peaks16 = _run(image.astype(np.uint16) * 16, min_height=128.0, min_slope=48.0)
    assert peaks16.n_peaks == peaks8.n_peaks
    assert np.allclose(peaks16.row, peaks8.row, atol=1e-6)


@pytest.mark.parametrize("bias", ["max-minimum", "min-minimum", "none"])
def test_bias_modes(bias: str) -> None:
    image, cols, rows = synthetic_lines(sigma=1.0, background=30.0)
    peaks = _run(image, bias=bias, bias_fraction=0.0 if bias == "none" else 0.1)
    err = _match(peaks, cols, rows)
    assert peaks.n_peaks == rows.size
    light = _run(image)
    if bias == "none":
        # the background stays in: larger areas, and the row is pulled towards the wider side
        assert np.median(peaks.area) > 1.5 * np.median(light.area)
        assert np.sqrt(np.mean(err**2)) > 0.1
    else:
        assert np.sqrt(np.mean(err**2)) < 0.03


def test_wide_peaks_need_a_wider_window() -> None:
    # lines 40 px apart with sigma 4 px (a 5 MP sensor): the default window cuts them
    image, cols, rows = synthetic_lines((400, 30), spacing=40.0, sigma=4.0, tilt=0.02)
    peaks = _run(image, max_width=100, min_slope=0.7)
    err = _match(peaks, cols, rows)
    assert peaks.n_peaks == rows.size
    assert np.sqrt(np.mean(err**2)) < 0.05


def _sharp_column(centre: float, n: int = 40, sigma: float = 0.35) -> np.ndarray:
    """One column with a line sharper than a pixel (Gaussian ``sigma`` px), integrated over
    the pixels."""
    from math import erf, sqrt

    edges = np.arange(n + 1) - 0.5
    cdf = np.array([0.5 * (1.0 + erf((e - centre) / (sigma * sqrt(2.0)))) for e in edges])
    return (12.0 + 180.0 * np.diff(cdf)).astype(np.float32)[:, None]


@pytest.mark.parametrize("centre", [19.9, 20.1, 20.25, 19.7])
def test_line_sharper_than_a_pixel_is_found_at_its_centre(centre: float) -> None:
    pixels = np.repeat(_sharp_column(centre), 3, axis=1)
    found = detect_peaks(pixels)
    assert found.col.size == 3
    # the centroid of three pixels of so sharp a line is biased towards the pixel centre
    assert np.allclose(found.row, centre, atol=0.1)


def test_line_in_one_pixel_above_the_bias_is_found_only_with_narrow() -> None:
    pixels = np.repeat(_sharp_column(19.9, sigma=0.2), 3, axis=1)
    assert detect_peaks(pixels, narrow=False).col.size == 0
    found = detect_peaks(pixels)
    assert found.col.size == 3 and np.allclose(found.row, 19.9, atol=0.15)


def test_line_entirely_inside_one_pixel_is_not_told_from_a_hot_pixel() -> None:
    pixels = np.repeat(_sharp_column(20.0, sigma=0.05), 3, axis=1)
    assert detect_peaks(pixels).col.size == 0


def test_version_6_defaults() -> None:
    # results of version 5 in an archive are told from version 6's by the version
    assert FirstMomentPeaks.version == "6"
    p = FirstMomentPeaks.Params()
    assert (p.min_height, p.min_trust_height, p.min_slope, p.noise_factor) == (3, 3, 2, 5.7)
    assert p.smooth is False
    rule = (p.flank_tolerance, p.flank_span, p.flank_area_ratio, p.flank_run_on)
    assert rule == (0.4, 1.5, 1.5, 1.0)


def _two_lines(centre: float, gap: float, sigma: float) -> np.ndarray:
    rows = np.arange(60, dtype=np.float64)[:, None]
    column = 10.0 + sum(
        60.0 * np.exp(-0.5 * ((rows - c) / sigma) ** 2) for c in (centre, centre + gap)
    )
    return np.repeat(column, 4, axis=1).astype(np.uint8)


@pytest.mark.parametrize("sigma", [1.0, 2.0, 6.0])
def test_raw_columns_find_no_noise_peaks_with_the_raised_factor(sigma: float) -> None:
    # the [1, 2, 1] / 4 smoothing lowers the noise to 0.61 of itself: 3.5 times it on the
    # smoothed column is 5.7 times it on the raw one
    rng = np.random.default_rng(7)
    pixels = np.clip(rng.normal(40.0, sigma, (604, 576)), 0, 255).astype(np.uint8)
    assert _run(pixels, noise_factor=3.5).n_peaks > 40
    assert _run(pixels).n_peaks == 0


def test_two_close_lines_are_not_one_peak_between_them() -> None:
    # two lines 2.5 px apart where the back turns away: the smoothed column of version 5
    # holds one maximum between them, a peak 1.25 px off both lines; on the raw column the
    # one line that rises above its minima is crowded by the other (its bounding minima
    # differ): dropped as untrustworthy, not misplaced
    pixels = _two_lines(20.3, 2.5, 0.7)
    merged = _run(pixels, **VERSION_5)
    assert merged.n_peaks == 4 and np.allclose(merged.row, 21.56, atol=0.01)
    found = _run(pixels)
    assert found.n_peaks == 0 and found.dropped == 4


@pytest.mark.parametrize("params", [{}, VERSION_5])
def test_two_lines_three_pixels_apart_are_two_peaks(params: dict) -> None:
    found = _run(_two_lines(20.3, 3.0, 0.7), **params)
    assert found.n_peaks == 8
    assert np.abs(np.sort(found.row[found.col == 0]) - [20.3, 23.3]).max() < 0.05


@pytest.mark.parametrize("height", [5.0, 6.0])
def test_dim_narrow_line_is_found_on_the_raw_column(height: float) -> None:
    # a line sharper than a pixel, a few DN high: the [1, 2, 1] smoothing of version 5
    # flattened it under the least height
    rows = np.arange(60, dtype=np.float64)[:, None]
    pixels = np.repeat(10.0 + height * np.exp(-0.5 * ((rows - 20.3) / 0.45) ** 2), 4, axis=1)
    pixels = pixels.astype(np.uint8)
    assert _run(pixels, **VERSION_5).n_peaks == 0
    found = _run(pixels)
    assert found.n_peaks == 4 and np.abs(found.row - 20.3).max() < 0.2


SCENES = Path(__file__).resolve().parents[1] / "data" / "scenes"


def _back_crossings_found(frame: np.lib.npyio.NpzFile, peaks: Peaks) -> int:
    """The back's exact line crossings with a peak within 1.5 px in their column."""
    back = frame["lr_on_back"]
    key = np.sort(peaks.col.astype(np.int64) * 100_000 + peaks.row)
    want = frame["lr_column"][back].astype(np.int64) * 100_000 + frame["lr_row"][back]
    j = np.clip(np.searchsorted(key, want), 1, key.size - 1)
    nearest = np.minimum(np.abs(key[j - 1] - want), np.abs(key[j] - want))
    return int(np.count_nonzero(nearest < 1.5))


@pytest.mark.parametrize("name", ["scene-7408-mseq8b-35to65", "scene-44157-mseq8b-35to65"])
def test_kept_clinic_frames_of_close_lines_find_more_of_the_back(name: str) -> None:
    # clinic frames through the tuning twin of the raster with the closest lines (kept in
    # tests/data/scenes): version 6 finds a peak at 58-69 more of the back's crossings
    with np.load(SCENES / f"{name}.npz") as frame:
        image = frame["image"]
        before = _back_crossings_found(frame, _run(image, **VERSION_5))
        after = _back_crossings_found(frame, _run(image))
    assert after >= before + 50
