"""The measured trunk: which cells of a back's height field are trunk, its outline and centre.

A rasterstereograph shows the trunk and, beside it, the arms; the raster lines break in the
gaps between them and jump in depth where an arm lies in front of the flank. The landmark
search regions are derived from the trunk found here (its height, its outline per horizontal
row, its centre line) rather than from fixed world coordinates, so they follow the patient
wherever he stands and whatever his size.

Per horizontal row (rows of the level grid are perpendicular to gravity, see
:mod:`rasterserver_plugins.level_frame`) the trunk is the run of measured cells that
contains the row's centre, a run ending at a hole or at a depth jump steeper than
``max_slope``; the centre is first the median column of the largest connected measured
region, then the smoothed middle of the runs themselves (two passes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import label, median_filter, uniform_filter1d

__all__ = ["MAX_STRAIGHT_EDGE", "Trunk", "find_trunk"]

#: Share of the trunk's height above which a straight vertical edge means a cut-off back
#: (at most 0.4 on the simulated backs, whole or with arms; 1.0 for half a back).
MAX_STRAIGHT_EDGE = 0.6


@dataclass(frozen=True)
class Trunk:
    """The trunk in a height field's grid.

    Attributes
    ----------
    mask : numpy.ndarray
        ``(ny, nx)`` bool trunk cells.
    left, right : numpy.ndarray
        ``(ny,)`` float first and last column of the trunk's run in each row (NaN in rows
        without trunk).
    centre : numpy.ndarray
        ``(ny,)`` float column of the trunk's centre, smoothed along the height (NaN in rows
        without trunk).
    top, bottom : int
        First and last row with trunk (``-1`` when there is none).
    half_width : numpy.ndarray
        ``(ny,)`` half-width of the trunk's run (mm; NaN in rows without trunk).
    spacing : float
        Grid step (mm).
    reason : str
        Why no trunk was found, or "".
    cut : str
        ``"left"`` or ``"right"`` (the patient's, ``-x`` or ``+x``) when the trunk ends on that
        side, and only that side, at a straight vertical edge over more than
        :data:`MAX_STRAIGHT_EDGE` of its height: the image or the measured area cuts the back
        off (no body outline is straight over that length); "" otherwise.
    """

    mask: np.ndarray
    left: np.ndarray
    right: np.ndarray
    centre: np.ndarray
    top: int
    bottom: int
    half_width: np.ndarray
    spacing: float
    reason: str = ""
    cut: str = ""

    @property
    def found(self) -> bool:
        """Whether a trunk was found."""
        return self.top >= 0

    @property
    def height(self) -> float:
        """Height of the measured trunk (mm)."""
        return 0.0 if not self.found else (self.bottom - self.top + 1) * self.spacing

    def reference_half_width(self) -> float:
        """Median half-width over the trunk's rows (mm): the trunk's size."""
        w = self.half_width[np.isfinite(self.half_width)]
        return float(np.median(w)) if w.size else float("nan")


def _runs(valid: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last column of the run of ``valid`` holding (or nearest to) ``centre``."""
    ny, nx = valid.shape
    cols = np.arange(nx)
    starts = valid & ~np.concatenate([np.zeros((ny, 1), bool), valid[:, :-1]], axis=1)
    run_id = np.cumsum(starts, axis=1)
    has = valid.any(axis=1) & np.isfinite(centre)
    c = np.where(has, centre, 0.0)
    nearest = np.where(valid, np.abs(cols[None, :] - c[:, None]), np.inf).argmin(axis=1)
    target = run_id[np.arange(ny), nearest]
    sel = valid & (run_id == target[:, None]) & has[:, None]
    left = np.where(has, sel.argmax(axis=1), np.nan)
    right = np.where(has, nx - 1 - sel[:, ::-1].argmax(axis=1), np.nan)
    return left, right


def find_trunk(
    z: np.ndarray,
    spacing: float,
    *,
    max_slope: float = 2.5,
    min_width: float = 60.0,
    min_area: float = 15000.0,
    max_hole: float = 30.0,
) -> Trunk:
    """Find the trunk in a height field.

    Parameters
    ----------
    z : numpy.ndarray
        ``(ny, nx)`` depth (mm) on the level grid; NaN where not measured.
    spacing : float
        Grid step (mm).
    max_slope : float, optional
        A step between neighbouring cells of a row steeper than this (``|Δz| / spacing``)
        separates two objects (an arm in front of the flank).
    min_width : float, optional
        Narrowest run (mm) counted as trunk.
    min_area : float, optional
        Smallest measured area (mm²) worth looking at.
    max_hole : float, optional
        Widest gap (mm) in a row, within a quarter of the trunk's width of its centre, that
        is taken as a hole in the back rather than its end.

    Returns
    -------
    Trunk
        The trunk, or one with ``top == -1`` and a reason.
    """
    ny, nx = z.shape
    max_bridge = max(1, int(max_hole / spacing))
    nan_rows = np.full(ny, np.nan)
    nothing = Trunk(
        np.zeros(z.shape, bool), nan_rows, nan_rows, nan_rows, -1, -1, nan_rows, spacing
    )
    valid = np.isfinite(z)
    if valid.sum() * spacing**2 < min_area:
        area = valid.sum() * spacing**2 / 100.0
        return _with_reason(nothing, f"only {area:.0f} cm² of surface measured")
    # Cut rows at depth jumps, so an arm in front of the flank is a separate object.
    with np.errstate(invalid="ignore"):
        jump = np.abs(np.diff(z, axis=1)) > max_slope * spacing
    cut = valid.copy()
    cut[:, 1:] &= ~jump
    labels, n = label(cut)
    if n == 0:
        return _with_reason(nothing, "no connected surface")
    sizes = np.bincount(labels.ravel())[1:]
    biggest = labels == (1 + int(np.argmax(sizes)))
    if biggest.sum() * spacing**2 < min_area:
        return _with_reason(nothing, "the largest connected piece of surface is too small")
    cols = np.nonzero(biggest)[1]
    centre = np.full(ny, float(np.median(cols)))
    span = float(np.ptp(cols)) + 1.0
    for _ in range(3):
        # Holes inside the back (a shadowed furrow, a lost line piece) must not cut a row's
        # run short: bridge short gaps near the centre line, where no arm can be.
        bridged = _bridge_inner_gaps(biggest, centre, reach=0.25 * span, longest=max_bridge)
        left, right = _runs(bridged, centre)
        width = (right - left + 1) * spacing
        rows = np.isfinite(width) & (width >= min_width)
        if not rows.any():
            return _with_reason(nothing, f"no row of the surface is {min_width:.0f} mm wide")
        mid = np.where(rows, 0.5 * (left + right), np.nan)
        # Fill rows without trunk from their neighbours, then smooth: arms that touch the
        # shoulders make single rows lopsided.
        good = np.flatnonzero(rows)
        filled = np.interp(np.arange(ny), good, mid[good])
        size = max(3, round(60.0 / spacing) | 1)
        centre = uniform_filter1d(median_filter(filled, size=size, mode="nearest"), size)
        span = float(np.median(right[rows] - left[rows] + 1))
    rows = _main_rows(rows)
    top, bottom = int(np.flatnonzero(rows)[0]), int(np.flatnonzero(rows)[-1])
    left = np.where(rows, left, np.nan)
    right = np.where(rows, right, np.nan)
    colgrid = np.arange(nx)[None, :]
    with np.errstate(invalid="ignore"):
        mask = rows[:, None] & (colgrid >= left[:, None]) & (colgrid <= right[:, None]) & valid
    # One straight side cuts a back off; two (a wall, a board filling the view) are no back
    # at all, which the landmark search will say.
    straight_left = _straight(left) > MAX_STRAIGHT_EDGE
    straight_right = _straight(right) > MAX_STRAIGHT_EDGE
    cut = ""
    if straight_left and not straight_right:
        cut = "left"
    elif straight_right and not straight_left:
        cut = "right"
    return Trunk(
        mask=mask,
        left=left,
        right=right,
        centre=np.where(rows, centre, np.nan),
        top=top,
        bottom=bottom,
        half_width=np.where(rows, 0.5 * (right - left + 1) * spacing, np.nan),
        spacing=spacing,
        cut=cut,
    )


def _straight(edge: np.ndarray) -> float:
    """Largest share of the rows whose edge lies within one column of a single column."""
    e = np.rint(edge[np.isfinite(edge)]).astype(int)
    if e.size == 0:
        return 0.0
    counts = np.bincount(e - e.min())
    near = counts + np.concatenate([[0], counts[:-1]]) + np.concatenate([counts[1:], [0]])
    return float(near.max() / e.size)


def _bridge_inner_gaps(
    valid: np.ndarray, centre: np.ndarray, *, reach: float, longest: int
) -> np.ndarray:
    """``valid`` with gaps of at most ``longest`` cells bridged where they lie within
    ``reach`` columns of ``centre`` (for finding runs only; depths are not invented)."""
    _, nx = valid.shape
    cols = np.arange(nx)
    # distance (cells) to the previous and next valid cell in the row
    last = np.where(valid, cols[None, :], -1)
    last = np.maximum.accumulate(last, axis=1)
    nxt = np.where(valid, cols[None, :], nx)
    nxt = np.minimum.accumulate(nxt[:, ::-1], axis=1)[:, ::-1]
    gap = nxt - last - 1
    near = np.abs(cols[None, :] - centre[:, None]) <= reach
    inner = (~valid) & (last >= 0) & (nxt < nx) & (gap <= longest) & near
    return valid | inner


def _main_rows(rows: np.ndarray) -> np.ndarray:
    """The trunk rows of the longest vertical stretch (gaps of up to 3 rows bridged)."""
    idx = np.flatnonzero(rows)
    stretches = np.split(idx, np.flatnonzero(np.diff(idx) > 3) + 1)
    longest = max(stretches, key=lambda b: b[-1] - b[0])
    out = np.zeros_like(rows)
    out[longest[0] : longest[-1] + 1] = True
    return out & rows


def _with_reason(trunk: Trunk, reason: str) -> Trunk:
    return Trunk(
        trunk.mask,
        trunk.left,
        trunk.right,
        trunk.centre,
        trunk.top,
        trunk.bottom,
        trunk.half_width,
        trunk.spacing,
        reason,
        trunk.cut,
    )
