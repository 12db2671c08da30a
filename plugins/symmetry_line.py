"""Hierholzer's symmetry line: the mirror axis of every horizontal profile of the back.

The back of a healthy subject is mirror-symmetric about the line of the spinous processes;
in scoliosis the trunk's cross-sections are shifted and turned, but each one stays close to
symmetric about the point where the spine meets the skin, in terms of the surface's
*intrinsic* shape. Hierholzer's symmetry line (Drerup & Hierholzer, *Back shape measurement
using video rasterstereography and three-dimensional reconstruction of spinal shape*, Clin
Biomech 9 (1994) 28-36; Hierholzer & Drerup, *High-resolution rasterstereography*, 1995)
is therefore found on every horizontal profile as the mirror axis that minimises the
**asymmetry of curvature** between each point and its mirror image, a function of the mean
curvature H, the curvature anisotropy ``(κ1 - κ2) / 2`` and the angle between the principal
directions of a point and of its mirrored partner.

We use the natural metric that combines exactly those three quantities: the distance
between the curvature tensor at ``P`` and the mirror image of the one at ``P'``. Writing the
traceless part of the curvature as the vector ``D = a (cos 2θ, sin 2θ)`` with
``a = (κ1 - κ2) / 2`` and ``θ`` the direction of ``κ1`` (mirroring about a vertical plane
maps ``θ`` to ``-θ``, i.e. ``D = (Dc, Ds)`` to ``(Dc, -Ds)``)::

    d²(P, P') = (H - H')² + (Dc - Dc')² + (Ds + Ds')²
              = (H - H')² + a² + a'² - 2 a a' cos 2Δθ

where ``Δθ`` is the angle between the principal direction at ``P`` and the mirrored one at
``P'``. A profile's asymmetry for a candidate axis ``x_s`` is the mean of ``d²`` over the
pairs ``x_s ± u`` (``u`` up to :data:`PAIR_REACH` of the trunk's half-width, both points
measured), divided by the mean of ``H² + a²`` over the same points, so 0 is perfect
symmetry and 1 no relation at all.

The axis is not chosen row by row, which would let a single noisy profile jump to another
minimum: a dynamic programme picks, over all profiles from VP to DM at once, the path of
axes with the least total asymmetry plus a penalty on the line's lateral slope; the chosen
axes are refined to a fraction of a cell (parabola through the asymmetry around the minimum)
and smoothed along the height. Profiles without measured pairs are bridged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from .curvature import Curvature
from .level_frame import LevelGrid, bilinear
from .trunk import Trunk

__all__ = [
    "EDGE_ROOM",
    "SymmetryLine",
    "curvature_features",
    "edge_room_reason",
    "find_symmetry_line",
    "profile_asymmetry",
]

#: Lateral reach of the mirrored pairs, as a fraction of the trunk's median half-width.
PAIR_REACH = 0.2
#: Nearest pair considered (mm): closer pairs mostly see the same smoothed curvature.
PAIR_MIN = 3.0
#: How far (fraction of the trunk's half-width) the axis may lie from the VP-DM line.
SEARCH_REACH = 0.6
#: Penalty of the dynamic programme on the squared lateral slope of the line (dx/dy)².
SLOPE_PENALTY = 0.15
#: Gaussian smoothing of the line along the height (mm).
SMOOTHING = 5.0
#: Least measured share of a candidate's pairs for its asymmetry to count.
MIN_PAIRS = 0.4
#: Least room (fraction of the trunk's median half-width) between the line and the measured
#: trunk's edge on either side. A spinous process lies half a back's width from the flanks;
#: a line closer to an edge than half the pairs' reach is the edge's artefact, its few
#: pairs symmetric by chance (held-out clinic body 43762, arms close and a 54 mm curve:
#: the line ran 7 mm from the trunk's edge where an arm cut it, 85 mm off the spine). On
#: 160 clinic tuning bodies and their backs alone the line kept 0.22 or more.
EDGE_ROOM = 0.1


@dataclass(frozen=True)
class SymmetryLine:
    """The symmetry line from VP down to DM, one point per horizontal profile.

    Attributes
    ----------
    x, y, z : numpy.ndarray
        ``(M,)`` level-frame points of the line (mm): ``y`` the profile's height, ``x`` the
        smoothed mirror axis, ``z`` the measured surface there.
    asymmetry : numpy.ndarray
        ``(M,)`` normalised asymmetry of the profile about the chosen axis (0 = symmetric),
        NaN for bridged profiles.
    raw_x : numpy.ndarray
        ``(M,)`` the axis per profile before smoothing (mm).
    reason : str
        Why there is no line, or "".
    """

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    asymmetry: np.ndarray
    raw_x: np.ndarray
    reason: str = ""

    @property
    def found(self) -> bool:
        """Whether the line exists."""
        return self.x.size > 0

    def points(self) -> np.ndarray:
        """``(M, 3)`` level points."""
        return np.column_stack([self.x, self.y, self.z])

    @classmethod
    def missing(cls, reason: str) -> SymmetryLine:
        """No line, saying ``reason``."""
        e = np.zeros(0)
        return cls(e, e, e, e, e, reason)


def curvature_features(curv: Curvature, rows: np.ndarray) -> np.ndarray:
    """``(3, R, nx)`` curvature features H, Dc, Ds of ``rows`` (see the module docstring)."""
    a = 0.5 * (curv.k1[rows] - curv.k2[rows])
    two = 2.0 * curv.direction[rows]
    return np.stack([curv.mean[rows], a * np.cos(two), a * np.sin(two)])


def profile_asymmetry(features: np.ndarray, *, reach: int, nearest: int = 1) -> np.ndarray:
    """Normalised curvature asymmetry of profiles about every axis of the grid.

    Parameters
    ----------
    features : numpy.ndarray
        ``(3, R, nx)`` features H, Dc, Ds of ``R`` profiles.
    reach : int
        Largest pair offset, in half-cells.
    nearest : int, optional
        Smallest pair offset, in half-cells.

    Returns
    -------
    numpy.ndarray
        ``(R, 2 nx - 1)`` asymmetry about the axes at columns ``0, 0.5, 1, ..., nx - 1``
        (NaN where fewer than :data:`MIN_PAIRS` of the pairs are measured).

    Notes
    -----
    The pair at offset ``m`` half-cells about the axis at half-cell ``k`` is the cells
    ``(k - m) / 2`` and ``(k + m) / 2`` (``k`` and ``m`` of the same parity), ``m`` cells
    apart: for a fixed ``m`` the pairs of all axes are the profiles against themselves
    shifted by ``m`` cells, so the whole table costs one vector operation per offset.
    """
    _, r, nx = features.shape
    h, dc, ds = features
    cell_energy = h * h + dc * dc + ds * ds
    n_axes = 2 * nx - 1
    num = np.zeros((r, n_axes))
    den = np.zeros((r, n_axes))
    n_ok = np.zeros((r, n_axes))
    n_all = np.zeros(n_axes)
    for m in range(max(nearest, 1), reach + 1):
        n_all[m % 2 :: 2] += 1
        if m >= nx:
            continue
        # cells l and l + m: the axis at half-cell 2 l + m
        lo, hi = slice(0, nx - m), slice(m, nx)
        d2 = (h[:, lo] - h[:, hi]) ** 2 + (dc[:, lo] - dc[:, hi]) ** 2
        d2 += (ds[:, lo] + ds[:, hi]) ** 2
        energy = cell_energy[:, lo] + cell_energy[:, hi]
        ok = np.isfinite(d2)
        axes = slice(m, m + 2 * (nx - m), 2)
        num[:, axes] += np.where(ok, d2, 0.0)
        den[:, axes] += np.where(ok, energy, 0.0)
        n_ok[:, axes] += ok
    with np.errstate(invalid="ignore", divide="ignore"):
        out = num / den
    return np.where((n_ok >= MIN_PAIRS * n_all) & (den > 0), out, np.nan)


def _best_path(cost: np.ndarray, penalty: np.ndarray) -> np.ndarray:
    """Indices (one per row) of the path minimising Σ cost + Σ penalty[|Δ index|]."""
    r, s = cost.shape
    step = np.abs(np.arange(s)[:, None] - np.arange(s)[None, :])
    trans = penalty[step]
    acc = cost[0].copy()
    back = np.zeros((r, s), dtype=np.intp)
    for i in range(1, r):
        total = acc[None, :] + trans  # [to, from]
        back[i] = np.argmin(total, axis=1)
        acc = total[np.arange(s), back[i]] + cost[i]
    path = np.empty(r, dtype=np.intp)
    path[-1] = int(np.argmin(acc))
    for i in range(r - 1, 0, -1):
        path[i - 1] = back[i, path[i]]
    return path


def find_symmetry_line(
    grid: LevelGrid,
    curv: Curvature,
    top: np.ndarray,
    bottom: np.ndarray,
    half_width: float,
) -> SymmetryLine:
    """The symmetry line between two landmarks (VP at the top, DM at the bottom).

    Parameters
    ----------
    grid : LevelGrid
        The surface in the level frame.
    curv : Curvature
        Its curvature maps (at the symmetry scale).
    top, bottom : numpy.ndarray
        ``(3,)`` level points of VP and DM.
    half_width : float
        The trunk's median half-width (mm): sets the pairs' reach and the search range.

    Returns
    -------
    SymmetryLine
        One point per grid row from VP's to DM's, or missing with a reason.
    """
    s = grid.spacing
    ny, nx = grid.shape
    r0 = int(np.ceil(float(grid.row_of(top[1]))))
    r1 = int(np.floor(float(grid.row_of(bottom[1]))))
    if r1 - r0 < 5:
        return SymmetryLine.missing("VP lies less than 5 profiles above DM")
    rows = np.arange(max(r0, 0), min(r1, ny - 1) + 1)
    ys = grid.y_of(rows)
    # The search follows the straight line VP-DM, up to SEARCH_REACH of the half-width away.
    frac = (ys - top[1]) / (bottom[1] - top[1])
    prior2 = np.rint(2.0 * grid.col_of(top[0] + frac * (bottom[0] - top[0]))).astype(int)
    half = int(np.ceil(2.0 * SEARCH_REACH * half_width / s))
    offsets = np.arange(-half, half + 1)
    axes2 = prior2[:, None] + offsets[None, :]
    reach = max(2, round(2.0 * PAIR_REACH * half_width / s))
    nearest = max(1, round(2.0 * PAIR_MIN / s))
    # Only the columns the candidate axes' pairs can reach.
    c0 = max(0, int(axes2.min()) // 2 - reach)
    c1 = min(nx, int(axes2.max()) // 2 + reach + 2)
    table = profile_asymmetry(
        curvature_features(curv, rows)[:, :, c0:c1], reach=reach, nearest=nearest
    )
    local = axes2 - 2 * c0
    inside = (local >= 0) & (local < table.shape[1])
    cost = np.where(
        inside, table[np.arange(rows.size)[:, None], np.clip(local, 0, table.shape[1] - 1)], np.nan
    )
    measured = np.isfinite(cost).any(axis=1)
    if measured.mean() < 0.5:
        return SymmetryLine.missing(
            f"only {100 * measured.mean():.0f}% of the profiles between VP and DM are measured "
            "on both sides"
        )
    filled = np.where(np.isfinite(cost), cost, 1.0)
    dx = np.arange(offsets.size) * s / 2.0  # lateral step per profile (mm) for |Δ index|
    path = _best_path(filled, SLOPE_PENALTY * (dx / s) ** 2)
    # Sub-half-cell refinement: vertex of the parabola through the cost around the minimum.
    idx = np.clip(path, 1, offsets.size - 2)
    c0, c1, c2 = (filled[np.arange(rows.size), idx + k] for k in (-1, 0, 1))
    denom = c0 - 2.0 * c1 + c2
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = np.where(denom > 0, 0.5 * (c0 - c2) / denom, 0.0)
    shift = np.where((path == idx) & (np.abs(shift) <= 1.0), shift, 0.0)
    raw2 = axes2[np.arange(rows.size), path] + shift
    raw_x = grid.x_of(raw2 / 2.0)
    asym = cost[np.arange(rows.size), path]
    good = measured
    x = np.interp(ys, ys[good], raw_x[good])
    x = gaussian_filter1d(x, SMOOTHING / s, mode="nearest")
    z = bilinear(grid.z, grid.col_of(x), rows.astype(float))
    if np.isnan(z).any():
        zs = bilinear(np.where(np.isfinite(curv.depth), curv.depth, np.nan), grid.col_of(x), rows)
        z = np.where(np.isfinite(z), z, zs)
        ok = np.isfinite(z)
        if ok.sum() >= 2:
            z = np.interp(ys, ys[ok], z[ok])
    return SymmetryLine(x=x, y=ys, z=z, asymmetry=np.where(good, asym, np.nan), raw_x=raw_x)


def edge_room_reason(line: SymmetryLine, grid: LevelGrid, trunk: Trunk, room: float) -> str:
    """Why the line is refused for running along the measured trunk's edge, or "".

    Parameters
    ----------
    line : SymmetryLine
        The symmetry line found.
    grid : LevelGrid
        The surface's grid.
    trunk : Trunk
        The trunk (its left and right edge per row).
    room : float
        Least distance to either edge, in trunk half-widths (:data:`EDGE_ROOM`); 0 does not
        check.

    Returns
    -------
    str
        The reason, or "" when the line keeps that room wherever the trunk is measured.
    """
    if room <= 0.0 or line.x.size == 0:
        return ""
    rows = np.clip(np.rint(grid.row_of(line.y)).astype(int), 0, grid.shape[0] - 1)
    left, right = grid.x_of(trunk.left[rows]), grid.x_of(trunk.right[rows])
    gap = np.minimum(line.x - left, right - line.x)
    w = trunk.reference_half_width()
    if not np.isfinite(gap).any() or np.nanmin(gap) >= room * w:
        return ""
    k = int(np.nanargmin(gap))
    return (
        f"the symmetry line runs {max(float(gap[k]), 0.0):.0f} mm from the measured trunk's "
        f"edge at height {line.y[k]:.0f} mm (less than {room * w:.0f} mm): the back beside "
        "it is not measured there (an arm close to the trunk, a shadow?), and a line along "
        "an edge is no mirror axis"
    )
