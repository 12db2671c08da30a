"""The surface grid's interpolation along and across the lines, compiled with numba.

:func:`rasterserver_plugins.smoothing.grid_from_lines` interpolated every line at every grid
column, then every grid column between neighbouring lines, with whole-array passes: stacks of
four nodes, slopes and Hermite terms for every (line, column) and every grid node, gathered
and masked again and again, ~7 of the surface stage's ~10 ms. These loops compute each node
once. Every value is the same expression in the same order as in those passes (the slopes,
the Hermite polynomial, the distances), so the grid is the same bits and the plugin's
version does not change.

Importing this module costs the numba import (~0.3 s): the surface stage imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel(error_model="numpy")
def _three_point_slope(d_prev: float, s_prev: float, d_next: float, s_next: float) -> float:
    return (d_prev * s_next + d_next * s_prev) / (d_prev + d_next)


@kernel(error_model="numpy")
def _hermite(t: float, h: float, f0: float, f1: float, m0: float, m1: float) -> float:
    t2 = t * t
    t3 = t2 * t
    return (
        (2 * t3 - 3 * t2 + 1) * f0
        + (t3 - 2 * t2 + t) * h * m0
        + (-2 * t3 + 3 * t2) * f1
        + (t3 - t2) * h * m1
    )


@kernel(error_model="numpy")
def _interval_slopes(
    x0: float,
    x1: float,
    x2: float,
    x3: float,
    f0: float,
    f1: float,
    f2: float,
    f3: float,
    has_prev: bool,
    has_next: bool,
) -> tuple[float, float]:
    # smoothing._interval_slopes for one interval (nodes 1 and 2; 0 and 3 beyond them)
    h0, h1, h2 = x1 - x0, x2 - x1, x3 - x2
    s0, s1, s2 = (f1 - f0) / h0, (f2 - f1) / h1, (f3 - f2) / h2
    if has_prev:
        m1 = _three_point_slope(h0, s0, h1, s1)
    elif has_next:
        m1 = s1 - (s2 - s1) * h1 / (h1 + h2)
    else:
        m1 = s1
    if has_next:
        m2 = _three_point_slope(h1, s1, h2, s2)
    elif has_prev:
        m2 = s1 + (s1 - s0) * h1 / (h0 + h1)
    else:
        m2 = s1
    return m1, m2


@kernel(error_model="numpy")
def _close(
    xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, a: int, b: int, max_gap2: float
) -> bool:
    dx, dy, dz = xs[a] - xs[b], ys[a] - ys[b], zs[a] - zs[b]
    return dx * dx + dy * dy + dz * dz <= max_gap2


@kernel(error_model="numpy")
def along_lines(
    key: np.ndarray,
    xs: np.ndarray,
    ys: np.ndarray,
    zs: np.ndarray,
    rk: np.ndarray,
    n_lines: int,
    nx: int,
    spacing: float,
    span: float,
    max_gap2: float,
    cubic: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """``y`` and ``z`` of every line at every grid column, ``(n_lines, nx)``, NaN where absent.

    Parameters
    ----------
    key : numpy.ndarray
        ``(N,)`` ascending sort key of the samples, ``rank * span + xs``.
    xs, ys, zs : numpy.ndarray
        ``(N,)`` the samples in key order; ``xs`` shifted so that grid column ``j`` lies at
        ``(j + 1) * spacing``.
    rk : numpy.ndarray
        ``(N,)`` int64 rank of each sample's line.
    n_lines, nx : int
        Lines and grid columns.
    spacing, span : float
        Grid step and the key's stride per line.
    max_gap2 : float
        Square of the largest 3-D distance between consecutive samples bridged.
    cubic : bool
        Cubic Hermite with three-point slopes, or linear.
    """
    n = key.shape[0]
    line_y = np.full((n_lines, nx), np.nan)
    line_z = np.full((n_lines, nx), np.nan)
    hi = 0
    for r in range(n_lines):
        for j in range(nx):
            xg = (j + 1.0) * spacing
            # np.searchsorted(key, q) ("left"), walking on from the previous node's position:
            # the nodes' keys ascend (a binary search per node cost more than the rest)
            q = r * span + xg
            if hi > 0 and key[hi - 1] >= q:
                hi = int(np.searchsorted(key, q))
            while hi < n and key[hi] < q:
                hi += 1
            lo = hi - 1
            hi_c, lo_c = min(hi, n - 1), max(lo, 0)
            on_hi = hi < n and rk[hi_c] == r
            exact = on_hi and xs[hi_c] == xg
            if exact:
                line_y[r, j] = ys[hi_c]
                line_z[r, j] = zs[hi_c]
                continue
            if not (on_hi and lo >= 0 and rk[lo_c] == r):
                continue
            if not _close(xs, ys, zs, lo_c, hi_c, max_gap2):
                continue
            dx = xs[hi_c] - xs[lo_c]
            t = (xg - xs[lo_c]) / dx if dx > 0 else 0.0
            if cubic:
                lp, hn = max(lo - 1, 0), min(hi + 1, n - 1)
                has_p = (
                    lo >= 1
                    and rk[lp] == r
                    and _close(xs, ys, zs, lp, lo_c, max_gap2)
                    and xs[lo_c] > xs[lp]
                )
                has_n = (
                    hi + 1 < n
                    and rk[hn] == r
                    and _close(xs, ys, zs, hn, hi_c, max_gap2)
                    and xs[hn] > xs[hi_c]
                )
                x0, x1, x2, x3 = xs[lp], xs[lo_c], xs[hi_c], xs[hn]
                m0, m1 = _interval_slopes(
                    x0, x1, x2, x3, ys[lp], ys[lo_c], ys[hi_c], ys[hn], has_p, has_n
                )
                line_y[r, j] = _hermite(t, dx, ys[lo_c], ys[hi_c], m0, m1)
                m0, m1 = _interval_slopes(
                    x0, x1, x2, x3, zs[lp], zs[lo_c], zs[hi_c], zs[hn], has_p, has_n
                )
                line_z[r, j] = _hermite(t, dx, zs[lo_c], zs[hi_c], m0, m1)
            else:
                line_y[r, j] = ys[lo_c] + t * (ys[hi_c] - ys[lo_c])
                line_z[r, j] = zs[lo_c] + t * (zs[hi_c] - zs[lo_c])
    return line_y, line_z


@kernel(error_model="numpy")
def _linked(
    line_y: np.ndarray,
    line_z: np.ndarray,
    lines: np.ndarray,
    a: int,
    b: int,
    col: int,
    max_line_step: int,
    max_distance2: float,
) -> bool:
    n_lines = line_y.shape[0]
    if a < 0 or b >= n_lines:
        return False
    dy = line_y[b, col] - line_y[a, col]
    dz = line_z[b, col] - line_z[a, col]
    return lines[b] - lines[a] <= max_line_step and dy > 0 and dy * dy + dz * dz <= max_distance2


@kernel(error_model="numpy")
def across_lines(
    line_y: np.ndarray,
    line_z: np.ndarray,
    lines: np.ndarray,
    y0: float,
    spacing: float,
    ny: int,
    max_line_step: int,
    max_distance2: float,
    cubic: bool,
) -> np.ndarray:
    """Depth of every grid node between neighbouring lines, ``(ny, nx)``, NaN elsewhere.

    Parameters
    ----------
    line_y, line_z : numpy.ndarray
        ``(n_lines, nx)`` from :func:`along_lines`.
    lines : numpy.ndarray
        ``(n_lines,)`` int64 line numbers, ascending.
    y0, spacing : float
        Grid origin and step along ``y``.
    ny : int
        Grid rows.
    max_line_step : int
        Largest difference of line numbers bridged.
    max_distance2 : float
        Square of the largest ``(y, z)`` distance between lines bridged.
    cubic : bool
        Cubic Hermite with three-point slopes, or linear.
    """
    n_lines, nx = line_y.shape
    z = np.full((ny, nx), np.nan)
    nxt = np.empty((n_lines, nx), dtype=np.int64)  # next valid line above in each column
    prv = np.empty((n_lines, nx), dtype=np.int64)  # previous valid line
    for col in range(nx):
        following = n_lines
        for r in range(n_lines - 1, -1, -1):
            nxt[r, col] = following
            if math.isfinite(line_y[r, col]):
                following = r
        preceding = -1
        for r in range(n_lines):
            prv[r, col] = preceding
            if math.isfinite(line_y[r, col]):
                preceding = r
    # pairs in (line, column) order, as np.nonzero gave them: where grid nodes of two
    # pairs coincide (folded lines), the later pair's value stands
    for ra in range(n_lines):
        for col in range(nx):
            if not math.isfinite(line_y[ra, col]):
                continue
            rb = nxt[ra, col]
            if rb >= n_lines:
                continue
            if not _linked(line_y, line_z, lines, ra, rb, col, max_line_step, max_distance2):
                continue
            ya, yb = line_y[ra, col], line_y[rb, col]
            za, zb = line_z[ra, col], line_z[rb, col]
            i_lo = math.ceil((ya - y0) / spacing)
            i_hi = math.ceil((yb - y0) / spacing)
            if i_hi <= i_lo:
                continue
            h = yb - ya
            m_a = m_b = 0.0
            if cubic:
                rp, rn = prv[ra, col], nxt[rb, col]
                has_p = _linked(line_y, line_z, lines, rp, ra, col, max_line_step, max_distance2)
                has_n = _linked(line_y, line_z, lines, rb, rn, col, max_line_step, max_distance2)
                rp, rn = min(max(rp, 0), n_lines - 1), min(max(rn, 0), n_lines - 1)
                y_p, y_n = line_y[rp, col], line_y[rn, col]
                z_p, z_n = line_z[rp, col], line_z[rn, col]
                m_a, m_b = _interval_slopes(y_p, ya, yb, y_n, z_p, za, zb, z_n, has_p, has_n)
            for i in range(max(i_lo, 0), min(i_hi, ny)):
                t = (y0 + i * spacing - ya) / h
                if cubic:
                    z[i, col] = _hermite(t, h, za, zb, m_a, m_b)
                else:
                    z[i, col] = za + t * (zb - za)
    return z
