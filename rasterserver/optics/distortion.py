"""The lens model of camera and projector: OpenCV's radial and tangential distortion of
normalised coordinates, its Jacobian, and its iterative inverse."""

from __future__ import annotations

import numpy as np

_UNDISTORT_TOL = 1e-13  # normalised units: ~1e-10 px at f = 2000 px
_UNDISTORT_MAX_ITER = 30


def as_points(points: np.ndarray, dim: int, what: str) -> np.ndarray:
    """``points`` as a float64 ``(N, dim)`` array, or a refusal naming ``what``."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim == 1 and arr.shape[0] == dim:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"{what} must have shape (N, {dim}), got {arr.shape}")
    return arr


def distort_normalized(
    x: np.ndarray, y: np.ndarray, dist: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the OpenCV distortion ``(k1, k2, p1, p2, k3)`` to ideal normalised coordinates.

    Parameters
    ----------
    x, y : numpy.ndarray
        Ideal normalised coordinates ``X/Z``, ``Y/Z`` (any matching shapes).
    dist : numpy.ndarray
        ``(5,)`` distortion coefficients.

    Returns
    -------
    xd, yd : numpy.ndarray
        Distorted normalised coordinates.
    """
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    r2 = x * x + y * y
    # the common one-term lens takes fewer passes over the renderer's big arrays
    one_term = k2 == 0.0 and k3 == 0.0
    radial = 1.0 + k1 * r2 if one_term else 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if p1 == 0.0 and p2 == 0.0:
        return x * radial, y * radial
    xy = x * y
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
    return xd, yd


def distortion_jacobian(
    x: np.ndarray, y: np.ndarray, dist: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Partial derivatives ``(dxd/dx, dxd/dy, dyd/dx, dyd/dy)`` of :func:`distort_normalized`."""
    k1, k2, p1, p2, k3 = (float(c) for c in dist)
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r2
    dxx = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
    dxy = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    dyx = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
    dyy = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
    return dxx, dxy, dyx, dyy


def undistort_normalized(
    xd: np.ndarray, yd: np.ndarray, dist: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort_normalized` by Newton's method (2x2 Jacobian per point).

    Converges to ~1e-13 normalised units (1e-10 px at f = 2000 px) for any distortion that is
    invertible over the field of view; ``cv2.undistortPoints`` stops far earlier.

    Parameters
    ----------
    xd, yd : numpy.ndarray
        Distorted normalised coordinates.
    dist : numpy.ndarray
        ``(5,)`` distortion coefficients.

    Returns
    -------
    x, y : numpy.ndarray
        Ideal normalised coordinates.
    """
    xd = np.asarray(xd, dtype=np.float64)
    yd = np.asarray(yd, dtype=np.float64)
    if not np.any(dist):
        return xd.copy(), yd.copy()
    x, y = xd.copy(), yd.copy()
    for _ in range(_UNDISTORT_MAX_ITER):
        fx_, fy_ = distort_normalized(x, y, dist)
        rx, ry = fx_ - xd, fy_ - yd
        a, b, c, d = distortion_jacobian(x, y, dist)
        det = a * d - b * c
        dx = (d * rx - b * ry) / det
        dy = (a * ry - c * rx) / det
        x -= dx
        y -= dy
        step = np.nanmax(np.abs(dx), initial=0.0) + np.nanmax(np.abs(dy), initial=0.0)
        if step < _UNDISTORT_TOL:
            break
    return x, y
