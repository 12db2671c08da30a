"""The compiled screening of reconstructed points against the passes it replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.point_screen import screened_points


def _passes(xyz: np.ndarray, v: np.ndarray, depth_limit: float) -> tuple:  # type: ignore[type-arg]
    """The screening of RayPlaneReconstruction.run of rasterserver 0.x."""
    unknown = np.isnan(v)
    finite = np.isfinite(xyz).all(axis=1)
    with np.errstate(invalid="ignore"):
        inside = np.abs(xyz[:, 2]) <= depth_limit
    keep = finite & inside
    counts = (
        int(np.count_nonzero(unknown)),
        int(np.count_nonzero(~finite & ~unknown)),
        int(np.count_nonzero(finite & ~inside)),
    )
    x, y, z = (np.ascontiguousarray(xyz[keep, i]) for i in range(3))
    return keep, x, y, z, counts


@pytest.mark.parametrize("seed", range(3))
def test_same_screening(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 5000
    xyz = rng.normal(0, 500, (n, 3))
    xyz[rng.random(n) < 0.05] = np.nan  # rays that missed
    xyz[rng.integers(0, n, 20), rng.integers(0, 3, 20)] = np.inf
    xyz[rng.integers(0, n, 20), 2] = 800.0  # at the limit: kept
    v = rng.uniform(0, 900, n)
    v[rng.random(n) < 0.03] = np.nan  # numbers the raster lacks (their rows are NaN too)
    xyz[np.isnan(v)] = np.nan
    got = screened_points(xyz, v, 800.0)
    want = _passes(xyz, v, 800.0)
    assert np.array_equal(got[0], want[0])
    for g, w in zip(got[1:4], want[1:4], strict=True):
        assert g.dtype == w.dtype and g.tobytes() == w.tobytes()
    assert got[4] == want[4] and all(c > 0 for c in want[4])


def test_none_and_one() -> None:
    for xyz, v in ((np.zeros((0, 3)), np.zeros(0)), (np.array([[1.0, 2.0, -3.0]]), np.ones(1))):
        got, want = screened_points(xyz, v, 800.0), _passes(xyz, v, 800.0)
        assert np.array_equal(got[0], want[0]) and got[4] == want[4]
        assert all(g.tobytes() == w.tobytes() for g, w in zip(got[1:4], want[1:4], strict=True))
