"""Newton's method on the ray parameter, one ray at a time, compiled with numba.

:meth:`rasterserver.optics.Projector.light_surface_intersection` with projector distortion
drives the projected diapositive ``v`` of a point on each camera ray to its raster line's
value. Vectorised over all rays, every iteration passed over the whole array, converged rays
included, until the slowest one converged: ~9 ms of the chain's ~40 on a 604 x 576 back.
Here each ray stops when it has converged. The arithmetic is the vectorised version's, term
by term and in the same order (numba without ``fastmath`` contracts nothing into fused
multiply-adds; division by zero gives inf or NaN as in numpy), so the points are
bit-identical to it; a ray's iterations never depended on the others' (a converged ray kept
its parameter), so stopping it early changes nothing.

Compiled on first use and cached beside this file (``__pycache__``); importing this module
costs the numba import (~0.3 s), so callers import it when they need it.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel(error_model="numpy")
def _distorted_y(
    x: float, y: float, k1: float, k2: float, p1: float, p2: float, k3: float
) -> float:
    # distort_normalized's y, with its branches: the one-term lens and the radial-only one
    r2 = x * x + y * y
    one_term = k2 == 0.0 and k3 == 0.0
    radial = 1.0 + k1 * r2 if one_term else 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if p1 == 0.0 and p2 == 0.0:
        return y * radial
    xy = x * y
    return y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy


@kernel(error_model="numpy")
def newton_on_rays(
    a: np.ndarray,
    b: np.ndarray,
    v_target: np.ndarray,
    s0: np.ndarray,
    fy: float,
    cy: float,
    dist: np.ndarray,
    tol: float,
    max_iter: int,
) -> np.ndarray:
    """Ray parameters where each ray's projected ``v`` is its target; NaN where none is.

    Parameters
    ----------
    a, b : numpy.ndarray
        ``(N, 3)`` float64 ray origins and directions in the projector's device frame.
    v_target : numpy.ndarray
        ``(N,)`` diapositive ``v`` of each ray's light surface.
    s0 : numpy.ndarray
        ``(N,)`` starting parameters (the undistorted plane's); NaN for no intersection.
    fy, cy : float
        The projector's focal length and principal point along ``v``.
    dist : numpy.ndarray
        ``(5,)`` OpenCV distortion ``(k1, k2, p1, p2, k3)``.
    tol : float
        Convergence tolerance on ``v`` (diapositive units).
    max_iter : int
        Newton steps at most per ray.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` parameters; NaN where Newton left the positive side of the ray or its
        final residual exceeds ``max(tol, 1e-7) * 10``.
    """
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    check = max(tol, 1e-7) * 10
    n = s0.shape[0]
    out = np.empty(n)
    for i in range(n):
        a0, a1, a2 = a[i, 0], a[i, 1], a[i, 2]
        b0, b1, b2 = b[i, 0], b[i, 1], b[i, 2]
        v = v_target[i]
        s = s0[i]
        for _ in range(max_iter):
            if math.isnan(s):
                break
            z = a2 + s * b2
            x = (a0 + s * b0) / z
            y = (a1 + s * b1) / z
            dx = (b0 - x * b2) / z
            dy = (b1 - y * b2) / z
            yd = _distorted_y(x, y, k1, k2, p1, p2, k3)
            r2 = x * x + y * y
            radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
            d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
            dyx = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
            dyy = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
            g = fy * yd + cy - v
            dg = fy * (dyx * dx + dyy * dy)
            if abs(g) < tol:
                break
            s = s - g / dg
            if not s > 0:
                s = np.nan
        # the last residual: Newton may have wandered (grazing rays)
        pz = a2 + s * b2
        yd = _distorted_y((a0 + s * b0) / pz, (a1 + s * b1) / pz, k1, k2, p1, p2, k3)
        out[i] = s if abs(fy * yd + cy - v) < check else np.nan
    return out
