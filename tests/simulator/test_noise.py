"""The sensor model: quantisation, clipping, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from rasterserver.simulator.noise import expected_statistics, expose

KW = {"gain": 0.01, "offset": 5.0, "read_noise": 10.0, "full_well": 20000.0}


def test_noise_free_is_rounding_only() -> None:
    e = np.array([[0.0, 1000.0, 12345.0, 1e6]])
    img = expose(e, rng=np.random.default_rng(0), bit_depth=8, noise=False, **KW)
    assert img.dtype == np.uint8
    assert img.tolist() == [[5, 15, 128, 205]]  # the last one saturates at the full well


def test_deterministic_per_seed_and_depths() -> None:
    e = np.full((50, 60), 8000.0)
    a = expose(e, rng=np.random.default_rng(3), bit_depth=12, **KW)
    b = expose(e, rng=np.random.default_rng(3), bit_depth=12, **KW)
    c = expose(e, rng=np.random.default_rng(4), bit_depth=12, **KW)
    assert a.dtype == np.uint16 and np.array_equal(a, b) and not np.array_equal(a, c)
    with pytest.raises(ValueError, match="bit depth"):
        expose(e, rng=np.random.default_rng(0), bit_depth=9, **KW)


def test_statistics_formula() -> None:
    e = np.full((400, 500), 5000.0)
    img = expose(e, rng=np.random.default_rng(5), bit_depth=16, **{**KW, "gain": 0.5})
    mean, var = expected_statistics(5000.0, gain=0.5, offset=5.0, read_noise=10.0)
    assert img.mean() == pytest.approx(float(mean), rel=1e-3)
    assert img.var() == pytest.approx(float(var), rel=0.02)
