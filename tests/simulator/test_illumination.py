"""The blurred raster transmission and its line look-ups against brute force."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from rasterserver.raster import default_raster, make_raster
from rasterserver.simulator.illumination import RasterLight


def brute_force(raster, v: np.ndarray, sigma: float) -> np.ndarray:  # type: ignore[no-untyped-def]
    s = np.sqrt(2.0) * sigma
    total = np.zeros_like(v)
    for c, w in zip(raster.positions, raster.widths, strict=True):
        total += 0.5 * (erf((v - c + w / 2) / s) - erf((v - c - w / 2) / s))
    return total


@pytest.mark.parametrize("sigma", [0.3, 0.6, 3.0])
def test_transmission_matches_brute_force(sigma: float) -> None:
    raster = default_raster()
    light = RasterLight(raster, defocus=sigma)
    v = np.random.default_rng(0).uniform(-50, 1050, 50_000)
    expected = brute_force(raster, v, sigma)
    np.testing.assert_allclose(light.transmission(v), expected, atol=1e-9)
    np.testing.assert_allclose(light.transmission_fast(v.astype(np.float32)), expected, atol=2e-4)


def test_line_lookups() -> None:
    raster = make_raster(30, window=7, spacing=8.0, centre=100.0)
    light = RasterLight(raster, defocus=0.5)
    v = np.random.default_rng(1).uniform(-20, 250, 20_000)
    nearest = np.argmin(np.abs(v[:, None] - raster.positions[None, :]), axis=1)
    np.testing.assert_array_equal(light.nearest(v), nearest)
    np.testing.assert_array_equal(
        light.count_at_or_below(v), np.searchsorted(raster.positions, v, side="right")
    )


def test_sharp_lines_and_nan() -> None:
    raster = default_raster()
    light = RasterLight(raster, defocus=0.0)
    c, w = raster.positions[10], raster.widths[10]
    v = np.array([c, c + 0.49 * w, c + 0.51 * w, np.nan])
    np.testing.assert_array_equal(light.transmission(v), [1.0, 1.0, 0.0, 0.0])
    assert light.transmission_fast(np.array([np.nan, -1e9], np.float32)).tolist() == [0.0, 0.0]
