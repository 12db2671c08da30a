"""The compiled per-ray Newton against the vectorised arithmetic it replaced: bit-identical."""

from __future__ import annotations

import numpy as np
import pytest

from rasterserver.optics import default_station
from rasterserver.optics.distortion import distort_normalized
from rasterserver.optics.light_surface_newton import newton_on_rays


def _vectorised(
    a: np.ndarray,
    b: np.ndarray,
    v_target: np.ndarray,
    s: np.ndarray,
    fy: float,
    cy: float,
    dist: np.ndarray,
    tol: float,
    max_iter: int,
) -> np.ndarray:
    """The whole-array Newton of rasterserver 0.x (Projector._newton_on_ray before numba)."""
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    a0, a1, a2 = (np.ascontiguousarray(a[:, k]) for k in range(3))
    b0, b1, b2 = (np.ascontiguousarray(b[:, k]) for k in range(3))
    s = s.copy()
    for _ in range(max_iter):
        z = a2 + s * b2
        with np.errstate(divide="ignore", invalid="ignore"):
            x = (a0 + s * b0) / z
            y = (a1 + s * b1) / z
            dx = (b0 - x * b2) / z
            dy = (b1 - y * b2) / z
        _, yd = distort_normalized(x, y, dist)
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        dyx = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        dyy = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        g = fy * yd + cy - v_target
        dg = fy * (dyx * dx + dyy * dy)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = g / dg
        converged = np.abs(g) < tol
        if np.all(converged | ~np.isfinite(s)):
            break
        s = np.where(converged, s, s - step)
        s = np.where(s > 0, s, np.nan)
    pc = a + s[:, None] * b
    with np.errstate(divide="ignore", invalid="ignore"):
        _, yd = distort_normalized(pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2], dist)
    bad = ~(np.abs(fy * yd + cy - v_target) < max(tol, 1e-7) * 10)
    s[bad] = np.nan
    return s


@pytest.mark.parametrize(
    "dist",
    [
        (-0.02, 0.0, 0.0, 0.0, 0.0),  # one-term lens
        (-0.02, 0.01, 0.0, 0.0, 0.003),  # radial only
        (-0.02, 0.01, 0.001, -0.0005, 0.0),  # tangential terms
    ],
)
@pytest.mark.parametrize("max_iter", [50, 2])
def test_same_bits_as_the_vectorised_newton(dist: tuple[float, ...], max_iter: int) -> None:
    st = default_station(projector_distortion=dist)
    proj = st.projector
    rng = np.random.default_rng(7)
    n = 5000
    # camera rays towards a back-sized field, some grazing, some pointing away, one NaN start
    o = np.broadcast_to(st.camera.centre, (n, 3))
    target = np.column_stack(
        [rng.uniform(-300, 300, n), rng.uniform(-400, 400, n), rng.uniform(-150, 150, n)]
    )
    d = target - o
    d[:50] *= -1.0
    a = np.ascontiguousarray(o @ proj.R.T + proj.t)
    b = np.ascontiguousarray(d @ proj.R.T)
    v = rng.uniform(0, proj.height, n)
    n_w, off = proj.light_plane(v)  # the undistorted plane's parameter, as the caller starts
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (off - np.einsum("ij,ij->i", n_w, o)) / np.einsum("ij,ij->i", n_w, d)
    s = np.where(np.isfinite(s) & (s > 0), s, np.nan)
    s[::3] *= rng.uniform(0.8, 1.2, s[::3].size)  # farther starts: more steps, some run out
    s[::97] = np.nan
    dist_arr = np.asarray(dist, dtype=np.float64)
    fy, cy = float(proj.K[1, 1]), float(proj.K[1, 2])
    want = _vectorised(a, b, v, s, fy, cy, dist_arr, 1e-7, max_iter)
    got = newton_on_rays(a, b, v, s, fy, cy, dist_arr, 1e-7, max_iter)
    assert np.isfinite(want).sum() > n // 4  # the comparison is about converged rays
    np.testing.assert_array_equal(got, want)  # NaN where NaN, every other bit equal


def test_empty_input() -> None:
    e = np.zeros((0, 3))
    out = newton_on_rays(e, e, np.zeros(0), np.zeros(0), 1000.0, 300.0, np.zeros(5), 1e-7, 50)
    assert out.shape == (0,)
