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
    points: Points,
    *,
    window: int = 3,
    step: int = 3,
    max_jump: float = 5.0,
    end_blocks: bool = False,
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
    end_blocks : bool, optional
        Where the steps leave a run's last peaks in no average, add one over its last
        ``window`` peaks: a run's end is then never more than ``window // 2`` columns from a
        point, whatever the run's length (without it, a gap filled by one peak can leave
        the joined run's last columns without a point and open a hole in the grid). Not
        used by the stage: measured, not adopted (BENCHMARKS.md "Real bodies",
        2026-11-30 (32): a pair of dimples 56 mm off on a tuning body).

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
    # the runs' kept centres and the means around them in compiled loops (run_means; the
    # numba import costs ~0.3 s, hence here)
    from .run_means import run_centres, window_means

    idx = run_centres(number, col, jump, window, step, end_blocks)
    if idx.size == 0:
        return points.take(
            np.zeros(0, dtype=np.intp),
            reason=_join(points.reason, f"no line has {window} peaks in neighbouring columns"),
        )
    # the peaks of each kept run: a sum of the few values averaged instead of a running sum
    # over every peak (same means within float rounding, ~1e-13 mm)
    x, y, z, row, area = window_means(
        order, idx, window, points.x, points.y, points.z, points.row, points.area
    )
    return Points(
        x=x,
        y=y,
        z=z,
        number=np.ascontiguousarray(number[idx], dtype=np.int32),
        col=col[idx].astype(np.int32),
        row=row,
        area=area.astype(np.float32),
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
    from .grid_interpolation import across_lines  # compiled; the numba import costs ~0.3 s

    x0, y0, nx, ny = _grid_frame(samples.x, samples.y, spacing)
    lines, rank = np.unique(samples.number, return_inverse=True)
    n_lines = lines.size
    line_y, line_z = _along_lines(samples, rank, n_lines, x0, nx, spacing, max_gap, cubic)
    z = across_lines(
        line_y,
        line_z,
        lines.astype(np.int64),
        float(y0),
        float(spacing),
        int(ny),
        int(max_line_step),
        float(max_line_distance) ** 2,
        bool(cubic),
    )
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
    from .grid_interpolation import along_lines  # compiled; the numba import costs ~0.3 s

    # one sorted key for all lines: rank * span + x keeps lines apart and x ascending inside
    span = (nx + 2) * spacing
    xs = samples.x - x0 + spacing
    key = rank * span + xs
    order = np.argsort(key, kind="stable")
    key, xs = key[order], xs[order]
    ys, zs, rk = samples.y[order], samples.z[order], rank[order]
    return along_lines(
        np.ascontiguousarray(key, dtype=np.float64),
        np.ascontiguousarray(xs, dtype=np.float64),
        np.ascontiguousarray(ys, dtype=np.float64),
        np.ascontiguousarray(zs, dtype=np.float64),
        np.ascontiguousarray(rk, dtype=np.int64),
        int(n_lines),
        int(nx),
        float(spacing),
        float(span),
        float(max_gap) ** 2,
        bool(cubic),
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
            data,
            window=params.window,
            step=params.step,
            max_jump=params.max_jump,
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
