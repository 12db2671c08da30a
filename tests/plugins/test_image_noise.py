"""The frame's pixel noise, estimated from the frame: against the noise put in."""

from __future__ import annotations

import numpy as np
import pytest
from image_truth import synthetic_lines
from rasterserver_plugins.image_noise import noise_level


@pytest.mark.parametrize("sigma", [1.0, 1.5, 2.0, 3.0, 8.0])
def test_pure_noise_is_measured(sigma: float) -> None:
    rng = np.random.default_rng(11)
    pixels = np.clip(rng.normal(60.0, sigma, (604, 576)), 0, 255).astype(np.uint8)
    assert noise_level(pixels) == pytest.approx(sigma, rel=0.08)


def test_float_image_gives_the_same_as_its_integer_copy() -> None:
    rng = np.random.default_rng(2)
    pixels = np.clip(rng.normal(60.0, 2.0, (200, 300)), 0, 255).astype(np.uint8)
    assert noise_level(pixels.astype(np.float64)) == pytest.approx(noise_level(pixels))


@pytest.mark.parametrize("tilt", [0.0, 0.05, 0.2])
def test_raster_lines_are_not_taken_for_noise(tilt: float) -> None:
    # bright tilted lines: their flanks must not read as noise (8-bit rounding of a
    # steep flank leaks a little: it stays below what would lift the peak stage's 3 DN
    # floor at its noise_factor of 3.5)
    clean, _, _ = synthetic_lines((400, 300), sigma=1.2, amplitude=150.0, tilt=tilt)
    assert noise_level(clean) < 0.8
    noisy, _, _ = synthetic_lines(
        (400, 300), sigma=1.2, amplitude=150.0, tilt=tilt, noise=2.0, seed=5
    )
    assert noise_level(noisy) == pytest.approx(2.0, rel=0.15)


@pytest.mark.parametrize(
    "pixels",
    [
        np.zeros((0, 5), np.uint8),
        np.zeros((5, 2), np.uint8),
        np.zeros((1, 1), np.uint8),
        np.zeros(7, np.uint8),
        np.full((50, 50), 255, np.uint8),
    ],
    ids=["no-rows", "two-columns", "1x1", "1-D", "saturated"],
)
def test_degenerate_images_have_no_noise(pixels: np.ndarray) -> None:
    assert noise_level(pixels) == 0.0
