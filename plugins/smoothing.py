"""Smoothing along the raster lines and interpolation onto a regular grid.

Two steps, after the seed:

1. **Linear smoothing along the lines.** About 25,000 peaks are reduced to one third: the
   reconstructed points of each line are averaged in runs of ``window`` neighbouring peaks
   (neighbouring image columns), and every ``step``-th run is kept. With ``window = step = 3``
   this is a block mean of three peaks, the same as a local linear fit over three equally
   spaced peaks evaluated at the middle one; it divides the depth noise by √3 and leaves
   ≈ 8,000 points. Runs never cross a gap in the line or a change of line number.
2. **Surface interpolation.** The smoothed points are interpolated onto a regular grid in
   world ``x, y`` (``spacing`` mm, origin on multiples of ``spacing``). The default method
   ``"lines"`` uses the raster's structure: each line is interpolated along its length at the
   grid columns, then each grid column is interpolated across neighbouring lines; a cell is
   filled only between two lines whose numbers are neighbours and not farther apart than
   ``max_line_distance``, and only where the lines have no gap wider than ``max_gap``. So
   holes (shadows, gaps between arm and trunk) stay holes. ``"delaunay"`` is scipy's linear
   ``griddata`` with cells farther than ``max_gap`` from any point masked, for point sets
   without line structure. An optional Gaussian (``sigma`` mm, NaN-aware) smooths the grid.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, field_validator

from rasterserver.records_surface import Points, Surface
from rasterserver.stage import Stage, StageContext, StageParams

__all__ = ["LinearGridSurface", "grid_from_lines", "smooth_along_lines"]


def smooth_along_lines(
    points: Points, *, window: int = 3, step: int = 3, max_jump: float = 5.0
) -> Points:
    """Average runs of ``window`` neighbouring peaks along each line, keeping every ``step``-th.

    Parameters
    ----------
    points : Points
        Reconstructed peaks.
    window : int, optional
        Peaks per average (odd, >= 1).
    step : int, optional
        Decimation: distance in peaks between the centres of kept averages (>= 1).
    max_jump : float, optional
        Largest 3-D distance (mm) between peaks of neighbouring columns averaged together;
        a larger step is a depth discontinuity (an arm in front of the trunk) and ends the run.

    Returns
    -------
    Points
        One point per kept run: mean ``x, y, z, row, area``, the run's centre column and its
        line number; sorted by line number, then column.
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be odd and positive, got {window}")
    if step < 1:
        raise ValueError(f"step must be positive, got {step}")
    n = len(points)
    if n == 0:
        return points.take(np.zeros(0, dtype=np.intp))
    width = int(points.col.max()) + 2
    key = points.number.astype(np.int64) * width + points.col.astype(np.int64)
    order = np.argsort(key, kind="stable")
    number = points.number[order]
    col = points.col[order].astype(np.int64)
    # a run is a stretch of one line over consecutive columns: a missing column, a second peak
    # in the same column or another number starts a new one
    xyz = np.column_stack([points.x[order], points.y[order], points.z[order]])
    jump = np.einsum("ij,ij->i", np.diff(xyz, axis=0), np.diff(xyz, axis=0)) > max_jump**2
    start = np.ones(n, dtype=bool)
    start[1:] = (np.diff(col) != 1) | (number[1:] != number[:-1]) | jump
    run = np.cumsum(start) - 1
    run_first = np.flatnonzero(start)
    run_len = np.diff(np.append(run_first, n))
    pos = np.arange(n) - run_first[run]
    half = window // 2
    centre = (pos >= half) & ((pos - half) % step == 0) & (pos + half < run_len[run])
    idx = np.flatnonzero(centre)
    if idx.size == 0:
        return points.take(
            np.zeros(0, dtype=np.intp),
            reason=_join(points.reason, f"no line has {window} peaks in neighbouring columns"),
        )

    # the peaks of each kept run, (window, runs): a gather of the few values averaged instead
    # of a running sum over every peak (same means within float rounding, ~1e-13 mm)
    members = order[idx[None, :] + np.arange(-half, half + 1)[:, None]]

    def mean(values: np.ndarray) -> np.ndarray:
        return values[members].sum(axis=0, dtype=np.float64) / window

    return Points(
        x=mean(points.x),
        y=mean(points.y),
        z=mean(points.z),
        number=np.ascontiguousarray(number[idx], dtype=np.int32),
        col=col[idx].astype(np.int32),
        row=mean(points.row),
        area=mean(points.area).astype(np.float32),
        image_shape=points.image_shape.copy(),
        reason=points.reason,
    )


def _join(*parts: str) -> str:
    return "; ".join(p for p in parts if p)


def _grid_frame(x: np.ndarray, y: np.ndarray, spacing: float) -> tuple[float, float, int, int]:
    x0 = float(np.floor(x.min() / spacing) * spacing)
    y0 = float(np.floor(y.min() / spacing) * spacing)
    nx = int(np.floor((x.max() - x0) / spacing)) + 1
    ny = int(np.floor((y.max() - y0) / spacing)) + 1
    return x0, y0, nx, ny


def _three_point_slope(
    d_prev: np.ndarray, s_prev: np.ndarray, d_next: np.ndarray, s_next: np.ndarray
) -> np.ndarray:
    """Derivative at a node from the secant slopes on both sides (exact for parabolas)."""
    return (d_prev * s_next + d_next * s_prev) / (d_prev + d_next)


def _hermite(
    t: np.ndarray, h: np.ndarray, f0: np.ndarray, f1: np.ndarray, m0: np.ndarray, m1: np.ndarray
) -> np.ndarray:
    """Cubic Hermite interpolation on ``[0, 1]`` of an interval of length ``h``."""
    t2 = t * t
    t3 = t2 * t
    return (
        (2 * t3 - 3 * t2 + 1) * f0
        + (t3 - 2 * t2 + t) * h * m0
        + (-2 * t3 + 3 * t2) * f1
        + (t3 - t2) * h * m1
    )


def _interval_slopes(
    x: np.ndarray, f: np.ndarray, has_prev: np.ndarray, has_next: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Slopes at both ends of the interval between nodes 1 and 2 of ``(4, K)`` nodes.

    Each end takes the slope of the parabola through it and its two neighbours (exact for
    parabolas); where node 0 or 3 is missing, the parabola through the three nodes that are
    there is used, and with only nodes 1 and 2 the secant (linear).
    """
    with np.errstate(invalid="ignore", divide="ignore"):
        h0, h1, h2 = x[1] - x[0], x[2] - x[1], x[3] - x[2]
        s0, s1, s2 = (f[1] - f[0]) / h0, (f[2] - f[1]) / h1, (f[3] - f[2]) / h2
        centred_1 = _three_point_slope(h0, s0, h1, s1)
        centred_2 = _three_point_slope(h1, s1, h2, s2)
        forward_1 = s1 - (s2 - s1) * h1 / (h1 + h2)  # parabola through 1, 2, 3 at node 1
        backward_2 = s1 + (s1 - s0) * h1 / (h0 + h1)  # parabola through 0, 1, 2 at node 2
    m1 = np.where(has_prev, centred_1, np.where(has_next, forward_1, s1))
    m2 = np.where(has_next, centred_2, np.where(has_prev, backward_2, s1))
    return m1, m2


def grid_from_lines(
    samples: Points,
    *,
    spacing: float,
    max_gap: float,
    max_line_step: int = 1,
    max_line_distance: float = 25.0,
    cubic: bool = True,
) -> tuple[float, float, np.ndarray]:
    """Interpolate points organised in numbered lines onto a regular ``(x, y)`` grid.

    Each line is interpolated along ``x`` at the grid columns (where its samples are at most
    ``max_gap`` apart in 3-D), then each grid column along ``y`` between lines that are
    neighbours: their numbers differ by at most ``max_line_step``, they are the closest such
    lines present in that column and at most ``max_line_distance`` apart in ``(y, z)`` (a
    larger step is a depth discontinuity, not surface). Both interpolations are cubic
    Hermite with three-point slopes (exact for parabolas, also at the ends of a line or of a
    run of lines: the lines are 10 mm apart and a back is curved on that scale) or, with
    ``cubic=False``, linear. A cubic interval uses only the two nodes around it and the one
    beyond each, all within the same gap limits.

    Parameters
    ----------
    samples : Points
        Points with line numbers (typically smoothed).
    spacing : float
        Grid step (mm).
    max_gap : float
        Largest ``x`` distance (mm) between consecutive samples of a line bridged.
    max_line_step : int, optional
        Largest difference of line numbers bridged (1: only adjacent lines).
    max_line_distance : float, optional
        Largest ``y`` distance (mm) between lines bridged.
    cubic : bool, optional
        Cubic Hermite (default) or linear interpolation.

    Returns
    -------
    x0, y0 : float
        Grid origin (multiples of ``spacing``).
    z : numpy.ndarray
        ``(ny, nx)`` float64 depths, NaN outside the measured surface.
    """
    x0, y0, nx, ny = _grid_frame(samples.x, samples.y, spacing)
    z = np.full((ny, nx), np.nan)
    lines, rank = np.unique(samples.number, return_inverse=True)
    n_lines = lines.size
    line_y, line_z = _along_lines(samples, rank, n_lines, x0, nx, spacing, max_gap, cubic)
    valid = np.isfinite(line_y)
    if n_lines < 2:
        return x0, y0, z
    # next / previous valid line of each (line, column): running min / max of valid ranks
    ranks = np.arange(n_lines)[:, None]
    nxt = np.minimum.accumulate(np.where(valid, ranks, n_lines)[::-1], axis=0)[::-1]
    nxt = np.vstack([nxt[1:], np.full((1, nx), n_lines)])
    prv = np.maximum.accumulate(np.where(valid, ranks, -1), axis=0)
    prv = np.vstack([np.full((1, nx), -1), prv[:-1]])

    def linked(r0: np.ndarray, r1: np.ndarray, col: np.ndarray) -> np.ndarray:
        ok = (r0 >= 0) & (r1 < n_lines)
        a, b = np.clip(r0, 0, n_lines - 1), np.clip(r1, 0, n_lines - 1)
        dy = line_y[b, col] - line_y[a, col]
        dz = line_z[b, col] - line_z[a, col]
        near = dy * dy + dz * dz <= max_line_distance**2
        return ok & (lines[b] - lines[a] <= max_line_step) & (dy > 0) & near

    r_a, col = np.nonzero(valid & (nxt < n_lines))
    r_b = nxt[r_a, col]
    pair = linked(r_a, r_b, col)
    r_a, r_b, col = r_a[pair], r_b[pair], col[pair]
    ya, yb = line_y[r_a, col], line_y[r_b, col]
    i_lo = np.ceil((ya - y0) / spacing).astype(np.int64)
    i_hi = np.ceil((yb - y0) / spacing).astype(np.int64)
    count = np.maximum(i_hi - i_lo, 0)
    rep = np.repeat(np.arange(count.size), count)
    i = i_lo[rep] + (np.arange(rep.size) - np.repeat(np.cumsum(count) - count, count))
    inside = (i >= 0) & (i < ny)
    rep, i = rep[inside], i[inside]
    h = yb - ya
    t = (y0 + i * spacing - ya[rep]) / h[rep]
    za, zb = line_z[r_a, col], line_z[r_b, col]
    if not cubic:
        z[i, col[rep]] = za[rep] + t * (zb[rep] - za[rep])
        return x0, y0, z
    r_p = prv[r_a, col]
    r_n = nxt[r_b, col]
    has_p = linked(r_p, r_a, col)
    has_n = linked(r_b, r_n, col)
    r_p, r_n = np.clip(r_p, 0, n_lines - 1), np.clip(r_n, 0, n_lines - 1)
    yy = np.stack([line_y[r_p, col], ya, yb, line_y[r_n, col]])
    zz = np.stack([line_z[r_p, col], za, zb, line_z[r_n, col]])
    m_a, m_b = _interval_slopes(yy, zz, has_p, has_n)
    z[i, col[rep]] = _hermite(t, h[rep], za[rep], zb[rep], m_a[rep], m_b[rep])
    return x0, y0, z


def _along_lines(
    samples: Points,
    rank: np.ndarray,
    n_lines: int,
    x0: float,
    nx: int,
    spacing: float,
    max_gap: float,
    cubic: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """``y`` and ``z`` of every line at every grid column, ``(n_lines, nx)``, NaN where absent."""
    # one sorted key for all lines: rank * span + x keeps lines apart and x ascending inside
    span = (nx + 2) * spacing
    xs = samples.x - x0 + spacing
    key = rank * span + xs
    order = np.argsort(key, kind="stable")
    key, xs = key[order], xs[order]
    ys, zs, rk = samples.y[order], samples.z[order], rank[order]
    n = key.size
    xg = np.tile((np.arange(nx) + 1.0) * spacing, n_lines)
    q_rank = np.repeat(np.arange(n_lines), nx)
    hi = np.searchsorted(key, q_rank * span + xg, side="left")
    lo = hi - 1
    hi_c, lo_c = np.minimum(hi, n - 1), np.maximum(lo, 0)
    on_hi = (hi < n) & (rk[hi_c] == q_rank)
    exact = on_hi & (xs[hi_c] == xg)
    dx = xs[hi_c] - xs[lo_c]

    def close(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d2 = (xs[a] - xs[b]) ** 2 + (ys[a] - ys[b]) ** 2 + (zs[a] - zs[b]) ** 2
        return d2 <= max_gap**2

    ok = on_hi & (lo >= 0) & (rk[lo_c] == q_rank) & close(lo_c, hi_c)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(dx > 0, (xg - xs[lo_c]) / dx, 0.0)
    if cubic:
        lp, hn = np.maximum(lo - 1, 0), np.minimum(hi + 1, n - 1)
        has_p = (lo >= 1) & (rk[lp] == q_rank) & close(lp, lo_c) & (xs[lo_c] > xs[lp])
        has_n = (hi + 1 < n) & (rk[hn] == q_rank) & close(hn, hi_c) & (xs[hn] > xs[hi_c])
        xx = np.stack([xs[lp], xs[lo_c], xs[hi_c], xs[hn]])
        out = []
        for f in (ys, zs):
            ff = np.stack([f[lp], f[lo_c], f[hi_c], f[hn]])
            m0, m1 = _interval_slopes(xx, ff, has_p, has_n)
            out.append(_hermite(t, dx, ff[1], ff[2], m0, m1))
        line_y, line_z = out
    else:
        line_y = ys[lo_c] + t * (ys[hi_c] - ys[lo_c])
        line_z = zs[lo_c] + t * (zs[hi_c] - zs[lo_c])
    line_y = np.where(exact, ys[hi_c], line_y)
    line_z = np.where(exact, zs[hi_c], line_z)
    valid = (ok | exact).reshape(n_lines, nx)
    return (
        np.where(valid, line_y.reshape(n_lines, nx), np.nan),
        np.where(valid, line_z.reshape(n_lines, nx), np.nan),
    )


def _grid_delaunay(
    samples: Points, *, spacing: float, max_gap: float
) -> tuple[float, float, np.ndarray]:
    from scipy.interpolate import griddata
    from scipy.spatial import cKDTree

    x0, y0, nx, ny = _grid_frame(samples.x, samples.y, spacing)
    gx, gy = np.meshgrid(x0 + spacing * np.arange(nx), y0 + spacing * np.arange(ny))
    xy = np.column_stack([samples.x, samples.y])
    if len(samples) < 3:
        return x0, y0, np.full((ny, nx), np.nan)
    z = griddata(xy, samples.z, (gx, gy), method="linear")
    dist, _ = cKDTree(xy).query(np.column_stack([gx.ravel(), gy.ravel()]))
    z[np.asarray(dist).reshape(ny, nx) > max_gap] = np.nan
    return x0, y0, z


def _gaussian_nan(z: np.ndarray, sigma_cells: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    valid = np.isfinite(z)
    num = gaussian_filter(np.where(valid, z, 0.0), sigma_cells, mode="constant", truncate=3.0)
    den = gaussian_filter(valid.astype(np.float64), sigma_cells, mode="constant", truncate=3.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(valid, num / den, np.nan)


def _cell_counts(
    samples: Points, x0: float, y0: float, spacing: float, shape: tuple[int, int]
) -> np.ndarray:
    ny, nx = shape
    # nearest node; samples beyond the last node's half cell still count for it
    j = np.clip(np.rint((samples.x - x0) / spacing).astype(np.int64), 0, nx - 1)
    i = np.clip(np.rint((samples.y - y0) / spacing).astype(np.int64), 0, ny - 1)
    flat = np.bincount(i * nx + j, minlength=ny * nx)
    return flat.reshape(ny, nx).astype(np.int32)


class LinearGridSurface(Stage[Points, Surface]):
    """Linear smoothing along the raster lines, then interpolation onto a regular grid."""

    name: ClassVar[str] = "surface.linear-grid"
    stage: ClassVar[str] = "surface"
    version: ClassVar[str] = "1"
    input_type = Points
    output_type = Surface

    class Params(StageParams):
        """Parameters of :class:`LinearGridSurface`."""

        window: int = Field(3, ge=1, le=31, description="Peaks averaged per sample (odd).")
        step: int = Field(3, ge=1, le=31, description="Keep every step-th average (decimation).")
        spacing: float = Field(3.0, ge=0.5, le=20.0, description="Grid step (mm).")
        method: Literal["lines", "delaunay"] = Field(
            "lines", description="Interpolation: along and across raster lines, or Delaunay."
        )
        max_jump: float = Field(
            5.0, gt=0, description="Largest 3-D step (mm) between peaks averaged together."
        )
        max_gap: float = Field(
            8.0, gt=0, description="Widest gap along a line (mm, 3-D) interpolated across."
        )
        max_line_step: int = Field(
            1, ge=1, le=5, description="Largest line-number difference interpolated across."
        )
        max_line_distance: float = Field(
            25.0, gt=0, description="Largest distance between lines (mm) interpolated across."
        )
        cubic: bool = Field(
            True, description="Cubic Hermite interpolation (method 'lines'); else linear."
        )
        sigma: float = Field(
            0.0, ge=0.0, le=50.0, description="Gaussian smoothing of the grid (mm); 0: none."
        )
        keep_samples: bool = Field(True, description="Store the smoothed points with the grid.")

        @field_validator("window")
        @classmethod
        def _odd(cls, value: int) -> int:
            if value % 2 == 0:
                raise ValueError("window must be odd (a centred run of peaks)")
            return value

    def run(self, data: Points, params: Params, context: StageContext) -> Surface:
        """Smooth ``data`` along its lines and grid it."""
        if len(data) == 0:
            return Surface.empty(_join("no points", data.reason), spacing=params.spacing)
        samples = smooth_along_lines(
            data, window=params.window, step=params.step, max_jump=params.max_jump
        )
        if len(samples) < 3:
            return Surface.empty(
                _join(f"only {len(samples)} smoothed points", samples.reason),
                spacing=params.spacing,
            )
        if params.method == "lines":
            x0, y0, z = grid_from_lines(
                samples,
                spacing=params.spacing,
                max_gap=params.max_gap,
                max_line_step=params.max_line_step,
                max_line_distance=params.max_line_distance,
                cubic=params.cubic,
            )
        else:
            x0, y0, z = _grid_delaunay(samples, spacing=params.spacing, max_gap=params.max_gap)
        if params.sigma > 0:
            z = _gaussian_nan(z, params.sigma / params.spacing)
        reason = samples.reason
        if not np.isfinite(z).any():
            reason = _join("no grid cell lies between two neighbouring lines", reason)
        keep = params.keep_samples
        return Surface(
            x0=x0,
            y0=y0,
            spacing=params.spacing,
            z=z,
            count=_cell_counts(samples, x0, y0, params.spacing, z.shape),
            samples=samples.xyz if keep else None,
            sample_number=samples.number if keep else None,
            sample_col=samples.col if keep else None,
            sample_row=samples.row if keep else None,
            sample_area=samples.area if keep else None,
            reason=reason,
        )
