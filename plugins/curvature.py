"""Curvature of a height field: local quadric fits, Monge-patch formulas, principal directions.

The back is measured as a height field ``z(x, y)`` (a Monge patch). Its differential geometry
follows from the first and second derivatives of ``z``; we take them from a **weighted local
quadric fit**: at every measured cell the polynomial ``a + b u + c v + d u² + e u v + f v²``
is fitted by least squares to the measured cells around it with Gaussian weights
``exp(-(u² + v²) / 2σ²)``. In the interior this is a derivative-of-Gaussian estimate at the
scale ``σ``; at the border of the measured area, and around holes, the fit simply uses the
cells that are there (a one-sided fit) instead of smoothing in the missing values as zeros,
so no garbage spreads from the holes (Farnebäck's normalised "polynomial expansion"). All
moments are separable Gaussian correlations, so the whole map costs a few milliseconds.

With ``z_x = b``, ``z_y = c``, ``z_xx = 2d``, ``z_xy = e``, ``z_yy = 2f`` and
``W = sqrt(1 + z_x² + z_y²)`` the Monge-patch formulas (do Carmo, *Differential Geometry of
Curves and Surfaces*, 1976, §3-3, Ex. 5) give

* Gaussian curvature ``K = (z_xx z_yy - z_xy²) / W⁴``;
* mean curvature ``H = ((1 + z_y²) z_xx - 2 z_x z_y z_xy + (1 + z_x²) z_yy) / (2 W³)``;
* principal curvatures ``κ1,2 = H ± sqrt(H² - K)`` (``κ1 ≥ κ2``) and their directions, the
  eigenvectors of the shape operator ``I⁻¹ II`` (first and second fundamental forms).

**Sign.** The normal used is ``(-z_x, -z_y, 1) / W``, pointing away from the camera into the
body. Since the camera looks at the back, a posterior bump has a depth *minimum*
(``z_xx > 0``), so ``H > 0`` is convex towards the camera (a bump: the vertebra prominens)
and ``H < 0`` concave (a dimple), as Drerup & Hierholzer (J Biomech 1987) map them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Curvature", "fit_quadric_at", "surface_curvature", "window_support"]

# Monomials u^a v^b of the quadric's basis (1, u, v, u², uv, v²), as exponent pairs.
_BASIS: tuple[tuple[int, int], ...] = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))


@dataclass(frozen=True)
class Curvature:
    """Curvature maps of a height field, NaN where not computed.

    Attributes
    ----------
    depth : numpy.ndarray
        ``(ny, nx)`` fitted (smoothed) depth ``z`` (mm).
    zx, zy : numpy.ndarray
        ``(ny, nx)`` slopes ``∂z/∂x`` and ``∂z/∂y``.
    zxx, zxy, zyy : numpy.ndarray
        ``(ny, nx)`` second derivatives (1/mm).
    mean, gaussian : numpy.ndarray
        ``(ny, nx)`` mean curvature H (1/mm, > 0 convex towards the camera) and Gaussian
        curvature K (1/mm²).
    k1, k2 : numpy.ndarray
        ``(ny, nx)`` principal curvatures, ``k1 ≥ k2`` (1/mm).
    direction : numpy.ndarray
        ``(ny, nx)`` angle (radians, in ``(-π/2, π/2]``) of the ``k1`` principal direction
        projected onto the ``(x, y)`` plane, from ``+x`` towards ``+y``; the ``k2`` direction
        is orthogonal on the surface.
    support : numpy.ndarray
        ``(ny, nx)`` share of the full Gaussian window's weight that fell on measured cells.
    sigma : float
        The fit's Gaussian scale (mm).
    depth_noise : float
        Estimated standard deviation of the measured depths about the fitted quadrics (mm):
        the measurement noise, plus detail finer than ``sigma``.
    noise : float
        The standard deviation (1/mm) that ``depth_noise`` causes in the mean curvature: a
        curvature extreme must stand well above it to be a feature, not noise.
    """

    depth: np.ndarray
    zx: np.ndarray
    zy: np.ndarray
    zxx: np.ndarray
    zxy: np.ndarray
    zyy: np.ndarray
    mean: np.ndarray
    gaussian: np.ndarray
    k1: np.ndarray
    k2: np.ndarray
    direction: np.ndarray
    support: np.ndarray
    sigma: float
    depth_noise: float = 0.0
    noise: float = 0.0

    @property
    def valid(self) -> np.ndarray:
        """``(ny, nx)`` bool: cells with curvature."""
        return np.isfinite(self.mean)

    def normal(self) -> np.ndarray:
        """``(ny, nx, 3)`` unit surface normals facing the camera, ``(z_x, z_y, -1) / W``."""
        w = np.sqrt(1.0 + self.zx**2 + self.zy**2)
        return np.stack([self.zx / w, self.zy / w, -1.0 / w], axis=-1)


def _kernels(sigma_cells: float, radius: int) -> dict[int, np.ndarray]:
    """1-D Gaussian kernels times ``(offset / σ)^p`` for p = 0..4 (offsets in units of σ)."""
    t = np.arange(-radius, radius + 1) / sigma_cells
    g = np.exp(-0.5 * t * t)
    return {p: g * t**p for p in range(5)}


def _moment(field: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    """``Σ field(i + v, j + u) kx(u) ky(v)``: a separable correlation, zero outside the grid.

    OpenCV's separable filter (a correlation, not a convolution) is ten times faster than
    scipy.ndimage's on these small grids.
    """
    return cv2.sepFilter2D(field, cv2.CV_64F, kx, ky, borderType=cv2.BORDER_CONSTANT)


def _solve_spd(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve many small symmetric positive definite systems ``a x = b`` at once.

    ``a`` is ``(k, k, n)`` and ``b`` ``(k, n)`` (the system index last, so every step is a
    contiguous vector operation): Gaussian elimination without pivoting, which SPD matrices
    do not need; for 6×6 systems far faster than one LAPACK call per system. ``a`` and ``b``
    are overwritten.
    """
    k = a.shape[0]
    for p in range(k):
        for r in range(p + 1, k):
            f = a[r, p] / a[p, p]
            a[r, p:] -= f * a[p, p:]
            b[r] -= f * b[p]
    x = np.empty_like(b)
    for p in range(k - 1, -1, -1):
        x[p] = (b[p] - (a[p, p + 1 :] * x[p + 1 :]).sum(axis=0)) / a[p, p]
    return x


def surface_curvature(
    z: np.ndarray,
    spacing: float,
    *,
    sigma: float = 10.0,
    min_support: float = 0.45,
    mask: np.ndarray | None = None,
) -> Curvature:
    """Curvature maps of the height field ``z`` from Gaussian-weighted local quadric fits.

    Parameters
    ----------
    z : numpy.ndarray
        ``(ny, nx)`` depths (mm) on a square grid; NaN where not measured.
    spacing : float
        Grid step (mm).
    sigma : float, optional
        Gaussian scale of the fit (mm). About the size of the features sought: 10 mm keeps
        the vertebra prominens and the lumbar dimples (a few mm deep, ~10 mm wide) and
        suppresses the measurement noise.
    min_support : float, optional
        Least share of the full window's weight that must fall on measured cells; below it
        (far beyond the border, in narrow strips) the cell gets NaN.
    mask : numpy.ndarray, optional
        ``(ny, nx)`` bool cells to use (default: the finite ones); curvature is computed only
        on them.

    Returns
    -------
    Curvature
        The maps; NaN outside ``mask`` and where the support or the fit is insufficient.

    Notes
    -----
    The least-squares normal equations at every cell need the weighted moments
    ``Σ w m u^a v^b`` (``a + b ≤ 4``) of the validity mask ``m`` and ``Σ w m z u^a v^b``
    (``a + b ≤ 2``); each is a separable correlation with a 1-D kernel ``t^p exp(-t²/2)``.
    Offsets are in units of ``σ`` so the 6×6 systems are well conditioned.
    """
    z = np.asarray(z, dtype=np.float64)
    valid = np.isfinite(z) if mask is None else (np.asarray(mask, bool) & np.isfinite(z))
    shape = z.shape
    nan = np.full(shape, np.nan)
    empty = Curvature(
        nan, nan, nan, nan, nan, nan, nan, nan, nan, nan, nan, np.zeros(shape), float(sigma)
    )
    if z.ndim != 2 or not valid.any():
        return empty
    s = sigma / spacing
    radius = max(1, int(np.ceil(3.0 * s)))
    k = _kernels(s, radius)
    m = valid.astype(np.float64)
    mz = np.where(valid, z, 0.0)
    full = float(k[0].sum() ** 2)
    # Moments of the mask: S[a, b] = Σ w m u^a v^b (u along x / columns, v along y / rows).
    moments = {(a, b): _moment(m, k[a], k[b]) for a in range(5) for b in range(5 - a)}
    support = moments[(0, 0)] / full
    # A quadric needs cells spread in both directions: the window's measured cells must not
    # lie nearly on a line (variance of their offsets, in units of sigma², at least 0.2).
    with np.errstate(invalid="ignore", divide="ignore"):
        s00 = moments[(0, 0)]
        var_u = moments[(2, 0)] / s00 - (moments[(1, 0)] / s00) ** 2
        var_v = moments[(0, 2)] / s00 - (moments[(0, 1)] / s00) ** 2
    cells = valid & (support >= min_support) & (var_u > 0.2) & (var_v > 0.2)
    if not cells.any():
        return empty
    idx = np.flatnonzero(cells)
    rhs = np.stack([_moment(mz, k[a], k[b]).ravel()[idx] for a, b in _BASIS])
    # Cells whose whole window is measured share one normal matrix: solve it once.
    inner = support.ravel()[idx] >= 1.0 - 1e-9
    coef = np.empty_like(rhs)
    a_full = np.array(
        [[float((k[a1 + a2].sum()) * (k[b1 + b2].sum())) for a2, b2 in _BASIS] for a1, b1 in _BASIS]
    )
    coef[:, inner] = np.linalg.solve(a_full, rhs[:, inner])
    edge = ~inner
    if edge.any():
        sel = idx[edge]
        normal = np.empty((6, 6, int(edge.sum())))
        for p, (a1, b1) in enumerate(_BASIS):
            for q, (a2, b2) in enumerate(_BASIS[p:], start=p):
                normal[p, q] = normal[q, p] = moments[(a1 + a2, b1 + b2)].ravel()[sel]
        coef[:, edge] = _solve_spd(normal, rhs[:, edge])
    coef = coef.T
    h = sigma  # offsets were in units of sigma (mm)
    c0 = coef[:, 0]
    depth_noise, noise = _noise(z.ravel()[idx][inner] - c0[inner], a_full, k, sigma)
    gx, gy = coef[:, 1] / h, coef[:, 2] / h
    gxx, gxy, gyy = 2.0 * coef[:, 3] / h**2, coef[:, 4] / h**2, 2.0 * coef[:, 5] / h**2
    out = _differential_geometry(gx, gy, gxx, gxy, gyy)

    def grid(values: np.ndarray) -> np.ndarray:
        g = np.full(shape, np.nan)
        g.ravel()[idx] = values
        return g

    return Curvature(
        depth=grid(c0),
        zx=grid(gx),
        zy=grid(gy),
        zxx=grid(gxx),
        zxy=grid(gxy),
        zyy=grid(gyy),
        mean=grid(out["mean"]),
        gaussian=grid(out["gaussian"]),
        k1=grid(out["k1"]),
        k2=grid(out["k2"]),
        direction=grid(out["direction"]),
        support=support,
        sigma=float(sigma),
        depth_noise=depth_noise,
        noise=noise,
    )


def _noise(
    residual: np.ndarray, a_full: np.ndarray, k: dict[int, np.ndarray], sigma: float
) -> tuple[float, float]:
    """Depth noise (mm) from the fits' residuals, and the mean curvature's noise (1/mm).

    The fits are linear in the depths: with ``A`` the full window's normal matrix and ``B``
    the same sums with squared weights, a depth noise ``s`` gives the coefficients the
    covariance ``s² A⁻¹ B A⁻¹``; in the interior ``H ≈ (d + f) / σ²`` and the residual at
    the centre has variance ``s² (1 − 2 l₀ + (A⁻¹ B A⁻¹)₀₀)``, ``l₀ = (A⁻¹)₀₀`` the centre's
    own weight in the fit. The residuals' spread is taken robustly (1.4826 × MAD).
    """
    if residual.size < 10:
        return 0.0, 0.0
    k2 = {p: k[0] * k[0] * (k[1] / np.where(k[0] > 0, k[0], 1.0)) ** p for p in range(5)}
    b_full = np.array(
        [[float(k2[a1 + a2].sum() * k2[b1 + b2].sum()) for a2, b2 in _BASIS] for a1, b1 in _BASIS]
    )
    a_inv = np.linalg.inv(a_full)
    cov = a_inv @ b_full @ a_inv
    mad = float(np.median(np.abs(residual - np.median(residual))))
    factor = 1.0 - 2.0 * a_inv[0, 0] + cov[0, 0]
    depth_noise = 1.4826 * mad / np.sqrt(max(factor, 1e-6))
    g = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 1.0]) / sigma**2
    return float(depth_noise), float(depth_noise * np.sqrt(g @ cov @ g))


def _differential_geometry(
    zx: np.ndarray, zy: np.ndarray, zxx: np.ndarray, zxy: np.ndarray, zyy: np.ndarray
) -> dict[str, np.ndarray]:
    """Monge-patch H, K, principal curvatures and the κ1 direction from the derivatives."""
    w2 = 1.0 + zx * zx + zy * zy
    w = np.sqrt(w2)
    gaussian = (zxx * zyy - zxy * zxy) / (w2 * w2)
    mean = ((1.0 + zy * zy) * zxx - 2.0 * zx * zy * zxy + (1.0 + zx * zx) * zyy) / (2.0 * w2 * w)
    root = np.sqrt(np.maximum(mean * mean - gaussian, 0.0))
    k1, k2 = mean + root, mean - root
    # Eigenvector of I⁻¹ II for κ1: (II - κ1 I) v = 0; take the better-conditioned row.
    e, f, g = 1.0 + zx * zx, zx * zy, 1.0 + zy * zy
    big_l, big_m, big_n = zxx / w, zxy / w, zyy / w
    a1, b1 = -(big_m - k1 * f), big_l - k1 * e
    a2, b2 = big_n - k1 * g, -(big_m - k1 * f)
    first = a1 * a1 + b1 * b1 >= a2 * a2 + b2 * b2
    vx, vy = np.where(first, a1, a2), np.where(first, b1, b2)
    direction = np.arctan2(vy, vx)
    direction = np.where(direction > np.pi / 2, direction - np.pi, direction)
    direction = np.where(direction <= -np.pi / 2, direction + np.pi, direction)
    return {"mean": mean, "gaussian": gaussian, "k1": k1, "k2": k2, "direction": direction}


def _window(
    z: np.ndarray,
    spacing: float,
    cols: np.ndarray,
    rows: np.ndarray,
    sigma: tuple[float, float],
    angle: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cells of a turned Gaussian window (three sigmas) around each point.

    Returns the depths, which of them are measured cells, the offsets ``u, v`` (mm) along the
    window's turned axes and the Gaussian weights, each ``(n, rows, cols)`` (``u, v`` and the
    weights broadcast against the others).
    """
    cols = np.atleast_1d(np.asarray(cols, dtype=float))
    rows = np.atleast_1d(np.asarray(rows, dtype=float))
    ny, nx = z.shape
    ca, sa = float(np.cos(angle)), float(np.sin(angle))
    # the bounding box of the turned 3-sigma window
    kx = max(1, int(np.ceil(3.0 * (sigma[0] * abs(ca) + sigma[1] * abs(sa)) / spacing)))
    ky = max(1, int(np.ceil(3.0 * (sigma[0] * abs(sa) + sigma[1] * abs(ca)) / spacing)))
    dj = np.arange(-kx, kx + 2)
    di = np.arange(-ky, ky + 2)
    j = np.floor(cols).astype(np.intp)[:, None, None] + dj[None, None, :]
    i = np.floor(rows).astype(np.intp)[:, None, None] + di[None, :, None]
    inside = (j >= 0) & (j < nx) & (i >= 0) & (i < ny)
    values = z[np.clip(i, 0, ny - 1), np.clip(j, 0, nx - 1)]
    du = (j - cols[:, None, None]) * spacing
    dv = (i - rows[:, None, None]) * spacing
    u = ca * du + sa * dv  # offsets along the (turned) window axes
    v = -sa * du + ca * dv
    w = np.exp(-0.5 * ((u / sigma[0]) ** 2 + (v / sigma[1]) ** 2))
    return values, inside & np.isfinite(values), u, v, w


def window_support(
    z: np.ndarray,
    spacing: float,
    cols: np.ndarray,
    rows: np.ndarray,
    sigma: tuple[float, float],
    *,
    angle: float = 0.0,
) -> np.ndarray:
    """The share of each half of a fit's window that lies on measured surface.

    The window is :func:`fit_quadric_at`'s (Gaussian scales ``sigma`` along its axes, turned by
    ``angle``); its halves are the sides ``u < 0`` and ``u > 0`` of its first axis, each
    weighted as the fit weights it. A fit whose window misses much of one half extrapolates
    that side: its slope across is then the other side's.

    Parameters
    ----------
    z : numpy.ndarray
        ``(ny, nx)`` depths (mm), NaN where not measured.
    spacing : float
        Grid step (mm).
    cols, rows : numpy.ndarray
        ``(n,)`` fractional positions of the points.
    sigma : tuple of float
        Gaussian scales (mm) along the window's axes.
    angle : float, optional
        The window's turn (radians), as in :func:`fit_quadric_at`.

    Returns
    -------
    numpy.ndarray
        ``(n, 2)`` shares (0 to 1) of the halves ``u < 0`` and ``u > 0``.
    """
    z = np.asarray(z, dtype=np.float64)
    _values, ok, u, _v, w = _window(z, spacing, cols, rows, sigma, angle)
    w = np.broadcast_to(w, ok.shape).reshape(ok.shape[0], -1)
    u = np.broadcast_to(u, ok.shape).reshape(ok.shape[0], -1)
    ok = ok.reshape(ok.shape[0], -1)
    out = np.zeros((ok.shape[0], 2))
    for k, half in enumerate((u < 0.0, u > 0.0)):
        total = np.where(half, w, 0.0).sum(axis=1)
        out[:, k] = np.where(half & ok, w, 0.0).sum(axis=1) / np.maximum(total, 1e-300)
    return out


def fit_quadric_at(
    z: np.ndarray,
    spacing: float,
    cols: np.ndarray,
    rows: np.ndarray,
    sigma: tuple[float, float],
    *,
    min_cells: int = 12,
    cubic: bool = False,
    angle: float = 0.0,
) -> np.ndarray:
    """Local quadric fits of the height field at arbitrary points.

    At each point ``(col, row)`` (fractional grid positions) the quadric
    ``a + b u + c v + d u² + e u v + f v²`` (``u, v`` in mm from the point along x and y) is
    fitted by least squares to the measured cells within three sigmas, with Gaussian weights
    of scales ``sigma = (σx, σy)`` (mm). ``b`` and ``c`` are then the slopes of the surface
    smoothed at that scale, whatever the point's position between cells.

    Parameters
    ----------
    z : numpy.ndarray
        ``(ny, nx)`` depths (mm), NaN where not measured.
    spacing : float
        Grid step (mm).
    cols, rows : numpy.ndarray
        ``(n,)`` fractional positions of the points.
    sigma : tuple of float
        Gaussian scales (mm) along x and y.
    min_cells : int, optional
        Fewest measured cells a fit needs.
    cubic : bool, optional
        Add the terms ``u³`` and ``u v²`` (odd in ``u``): the slope ``b`` then stays unbiased
        where the surface is a turned, curved cross-section (a rounded back turned about the
        vertical is no longer even about the turning point, and a quadric's slope would take
        up the odd part over a wide window).
    angle : float, optional
        Turn the window's axes by this angle (radians, from ``+x`` towards ``+y``): the
        Gaussian scales and the cubic terms then apply along the turned axes (a window
        aligned with a leaning trunk). The coefficients are returned in ``u, v`` all the same.

    Returns
    -------
    numpy.ndarray
        ``(n, 6)`` coefficients ``a, b, c, d, e, f`` (NaN rows where the fit is impossible).
    """
    z = np.asarray(z, dtype=np.float64)
    cols = np.atleast_1d(np.asarray(cols, dtype=float))
    ca, sa = float(np.cos(angle)), float(np.sin(angle))
    values, ok, u, v, w = _window(z, spacing, cols, rows, sigma, angle)
    w = np.where(ok, w, 0.0).reshape(cols.size, -1)
    zz = np.where(ok, values, 0.0).reshape(cols.size, -1)
    # scale offsets to units of sigma for conditioning
    uu = np.broadcast_to(u / sigma[0], ok.shape).reshape(cols.size, -1)
    vv = np.broadcast_to(v / sigma[1], ok.shape).reshape(cols.size, -1)
    terms = [np.ones_like(uu), uu, vv, uu * uu, uu * vv, vv * vv]
    if cubic:
        terms += [uu * uu * uu, uu * vv * vv]
    basis = np.stack(terms)  # (p, n, k)
    normal = np.einsum("pnk,qnk,nk->pqn", basis, basis, w)
    rhs = np.einsum("pnk,nk->pn", basis, w * zz)
    enough = ok.reshape(cols.size, -1).sum(axis=1) >= min_cells + 2 * cubic
    # keep impossible systems solvable, then blank them
    normal[:, :, ~enough] = np.eye(len(terms))[:, :, None]
    coef = _solve_spd(normal, rhs).T[:, :6]
    scale = np.array([1.0, sigma[0], sigma[1], sigma[0] ** 2, sigma[0] * sigma[1], sigma[1] ** 2])
    coef = coef / scale
    if angle:
        # back from the turned axes: gradient R^T g', Hessian R^T H' R
        rot = np.array([[ca, sa], [-sa, ca]])
        grad = coef[:, 1:3] @ rot
        hess = np.stack(
            [
                np.stack([2 * coef[:, 3], coef[:, 4]], -1),
                np.stack([coef[:, 4], 2 * coef[:, 5]], -1),
            ],
            axis=1,
        )
        hess = rot.T @ hess @ rot
        coef = np.column_stack(
            [coef[:, 0], grad, hess[:, 0, 0] / 2, hess[:, 0, 1], hess[:, 1, 1] / 2]
        )
    coef[~enough] = np.nan
    return coef
