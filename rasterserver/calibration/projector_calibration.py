"""Projector calibration from raster lines on the control planes.

The projector is an inverse camera whose "image" coordinate ``v`` is known for every point of
a raster line (the line's position in the diapositive, from the :class:`~rasterserver.raster.
Raster`). On a control plane of known position a line peak's 3-D point is the calibrated
camera's ray through it intersected with the plane; with the line's ``v`` this gives
``(X, v)`` pairs, and the projector is fitted to them:

1. a one-dimensional DLT (``v = p2 . X / p3 . X``, two rows of a projection matrix, linear in
   their 8 entries) starts the fit and checks the numbering;
2. least squares (``scipy.optimize.least_squares``) on the ``v`` residuals over the rotation,
   ``t_y``, ``t_z``, ``f_y``, ``c_y`` and the chosen distortion terms.

What lines cannot tell
----------------------
Lines are curves of constant ``v``: ``u`` is never observed. The light planes of a projector
without distortion form a pencil about the line through its centre parallel to its ``x``
axis, so the position of the centre *along* that axis (``t_x``), ``f_x`` and ``c_x`` do not
change any light plane, hence any reconstruction. They are taken from a *reference*
projector (the nominal design or the previous calibration): ``t_x`` is fixed so that the
centre keeps the reference's position along the projector's ``x`` axis, ``c_x`` and the
ratio ``f_x / f_y`` are copied. With distortion the light surfaces bend with ``x`` too, so
these values matter slightly; a reference within a few centimetres leaves the reconstruction
unchanged far below 0.01 mm.

Line numbering on the plates
----------------------------
The chain's numbering stage is not used here: on the calibration body the plates' line
pieces are continued by the base's lines beside them, so the code window reads across a depth
step and numbers whole plates wrongly by a constant. Instead each plate is numbered on its
own (:func:`number_plate_lines`): peaks inside the plate are linked column to column into
line pieces, pieces at the same height are merged into lines, the lines are ordered top to
bottom (``v`` grows downwards in the image, as for the patient chain), each line's kind
(light or heavy) is read from its median peak area against a smooth trend over the plate, and
the kind sequence is located in the raster's window code. A plate with fewer lines than the
code window, or whose sequence fits two places, is refused; a wrong numbering that slips
through shows as a gross DLT residual and is refused there.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from rasterserver.calibration.camera_calibration import DISTORTION_TERMS
from rasterserver.errors import InputError
from rasterserver.optics import Camera, Projector
from rasterserver.raster import Raster

__all__ = [
    "PlateLines",
    "ProjectorCalibration",
    "calibrate_projector",
    "dlt_1d",
    "group_lines",
    "intersect_plane",
    "number_plate_lines",
]


def group_lines(
    col: np.ndarray, row: np.ndarray, *, max_step: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Group the peaks of one flat plate into raster lines, ordered top to bottom.

    Parameters
    ----------
    col, row : numpy.ndarray
        ``(N,)`` peak columns (int) and sub-pixel rows of the plate's peaks.
    max_step : float, optional
        Largest row change between peaks of one line in neighbouring columns; by default
        a third of the typical line spacing in a column.

    Returns
    -------
    line : numpy.ndarray
        ``(N,)`` relative line index (0 = top), counting a missing line as a gap, or -1.
    heights : numpy.ndarray
        ``(L,)`` row of each line at the plate's mean column, by line index (NaN in gaps).
    """
    n = col.size
    if n == 0:
        return np.full(0, -1, np.int64), np.zeros(0)
    order = np.lexsort((row, col))
    col, row = col[order].astype(np.int64), row[order]
    same = np.diff(col) == 0
    gaps = np.diff(row)[same]
    spacing = float(np.median(gaps)) if gaps.size else 10.0
    step = spacing / 3.0 if max_step is None else max_step
    # link each peak to the nearest peak in the next column
    key = col * 1e6 + row
    target = (col + 1) * 1e6 + row
    pos = np.searchsorted(key, target)
    best = np.full(n, -1)
    best_d = np.full(n, np.inf)
    for cand in (pos - 1, pos):
        ok = (cand >= 0) & (cand < n)
        c = np.where(ok, cand, 0)
        d = np.where(ok & (col[c] == col + 1), np.abs(row[c] - row), np.inf)
        better = d < best_d
        best = np.where(better, c, best)
        best_d = np.where(better, d, best_d)
    link = best_d <= step
    src = np.flatnonzero(link)
    graph = coo_matrix((np.ones(src.size), (src, best[src])), shape=(n, n))
    _, piece = connected_components(graph, directed=False)
    # each piece's height at the reference column, from a straight fit (the plate is flat)
    ref = col.mean()
    counts = np.bincount(piece)
    sx = np.bincount(piece, col - ref)
    sy = np.bincount(piece, row)
    sxx = np.bincount(piece, (col - ref) ** 2)
    sxy = np.bincount(piece, (col - ref) * row)
    den = counts * sxx - sx**2
    long_ = (counts >= 5) & (den > 0)
    slope = np.where(long_, (counts * sxy - sx * sy) / np.where(den > 0, den, 1.0), np.nan)
    typical = float(np.nanmedian(slope)) if np.any(long_) else 0.0
    slope = np.where(np.isfinite(slope), slope, typical)
    height = (sy - slope * sx) / counts
    # merge pieces at the same height (a line interrupted by a hole) into lines
    by_height = np.argsort(height)
    sorted_h = height[by_height]
    new_line = np.concatenate([[True], np.diff(sorted_h) > spacing / 2.0])
    cluster_of_sorted = np.cumsum(new_line) - 1
    cluster = np.empty_like(cluster_of_sorted)
    cluster[by_height] = cluster_of_sorted
    weight = np.bincount(cluster, counts)
    centre = np.bincount(cluster, counts * height) / weight
    # keep lines with a fair share of peaks (drop specks); count a missed line as a gap
    keep = weight >= 0.2 * np.median(weight)
    kept = np.flatnonzero(keep)
    if kept.size == 0:
        return np.full(n, -1, np.int64), np.zeros(0)
    steps = np.diff(centre[kept])
    unit = float(np.median(steps)) if steps.size else spacing
    index = np.concatenate([[0], np.cumsum(np.maximum(np.rint(steps / unit), 1))]).astype(int)
    line_of_cluster = np.full(cluster.max() + 1, -1)
    line_of_cluster[kept] = index
    heights = np.full(index[-1] + 1, np.nan)
    heights[index] = centre[kept]
    line = np.empty(n, np.int64)
    line[order] = line_of_cluster[cluster[piece]]
    return line, heights


def _line_kinds(area: np.ndarray, line: np.ndarray, n_lines: int) -> np.ndarray:
    """Per line 1 (heavy), 0 (light) or -1 (no peaks), from median peak areas over a trend."""
    med = np.full(n_lines, np.nan)
    valid = line >= 0
    for j in np.unique(line[valid]):
        med[j] = np.median(area[line == j])
    have = np.isfinite(med) & (med > 0)
    bits = np.full(n_lines, -1, np.int64)
    if np.count_nonzero(have) < 4:
        return bits
    j = np.flatnonzero(have).astype(np.float64)
    y = np.log(med[have])
    design = np.column_stack([np.ones_like(j), j, j**2])
    heavy = y > np.median(y)
    # alternate: a smooth illumination trend, and a constant heavy/light step on top of it
    for _ in range(10):
        step = y[heavy].mean() - y[~heavy].mean() if heavy.any() and (~heavy).any() else 0.0
        coef, *_ = np.linalg.lstsq(design, y - step * heavy, rcond=None)
        rest = y - design @ coef
        new = rest > step / 2.0
        if np.array_equal(new, heavy):
            break
        heavy = new
    bits[have] = heavy.astype(np.int64)
    return bits


@dataclass(frozen=True, eq=False)
class PlateLines:
    """The numbered raster peaks on one plate.

    Attributes
    ----------
    pixels : numpy.ndarray
        ``(N, 2)`` peak positions ``(column, row)``.
    number : numpy.ndarray
        ``(N,)`` absolute line number.
    v : numpy.ndarray
        ``(N,)`` diapositive ``v`` of the line.
    offset : int
        Raster index of the plate's top line.
    mismatches : int
        Line kinds that disagree with the code at the chosen place.
    """

    pixels: np.ndarray
    number: np.ndarray
    v: np.ndarray
    offset: int
    mismatches: int


def number_plate_lines(
    col: np.ndarray,
    row: np.ndarray,
    area: np.ndarray,
    raster: Raster,
    *,
    name: str = "plate",
) -> PlateLines:
    """Number the raster lines on one flat plate by the light/heavy code of the raster.

    Parameters
    ----------
    col, row, area : numpy.ndarray
        ``(N,)`` the plate's peaks (column, sub-pixel row, area).
    raster : Raster
        The diapositive definition.
    name : str
        For messages.

    Returns
    -------
    PlateLines

    Raises
    ------
    InputError
        Too few lines to read the code, or a kind sequence that fits the code nowhere or in
        two places.
    """
    line, _ = group_lines(col, row)
    n_lines = int(line.max()) + 1 if line.size and line.max() >= 0 else 0
    if n_lines < raster.window:
        raise InputError(
            f"{name}: {n_lines} raster lines found, fewer than the code window of "
            f"{raster.window}: the plate is not lit by the projector or not visible"
        )
    bits = _line_kinds(area, line, n_lines)
    code = raster.code.astype(np.int64)
    places = raster.n_lines - n_lines + 1
    if places < 1:
        raise InputError(f"{name}: {n_lines} lines found but the raster has {raster.n_lines}")
    windows = np.lib.stride_tricks.sliding_window_view(code, n_lines)
    known = bits >= 0
    mismatches = np.count_nonzero((windows != bits[None, :]) & known[None, :], axis=1)
    ranked = np.argsort(mismatches, kind="stable")
    best = int(ranked[0])
    worst_allowed = max(1, np.count_nonzero(known) // 10)
    if mismatches[best] > worst_allowed:
        raise InputError(
            f"{name}: the light/heavy sequence of its {n_lines} lines fits the raster code "
            f"nowhere ({mismatches[best]} mismatches at best)"
        )
    if ranked.size > 1 and mismatches[ranked[1]] < mismatches[best] + 2:
        raise InputError(
            f"{name}: the light/heavy sequence of its {n_lines} lines fits the raster code "
            "in two places: cannot number the lines"
        )
    ok = line >= 0
    index = best + line[ok]
    return PlateLines(
        pixels=np.column_stack([col[ok], row[ok]]).astype(np.float64),
        number=raster.numbers[index],
        v=raster.positions[index],
        offset=best,
        mismatches=int(mismatches[best]),
    )


def intersect_plane(
    camera: Camera, pixels: np.ndarray, normal: np.ndarray, offset: float
) -> np.ndarray:
    """World points where the camera's rays through ``pixels`` meet the plane ``n @ p = d``."""
    origins, directions = camera.rays(pixels)
    s = (offset - origins @ normal) / (directions @ normal)
    return origins + s[:, None] * directions


def dlt_1d(xyz: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rows 2 and 3 of a projection matrix from points and one image coordinate.

    Solves ``v (p3 . X) = p2 . X`` (homogeneous, Hartley-normalised) for ``(p2, p3)``.

    Returns
    -------
    numpy.ndarray
        ``(2, 4)`` ``[p2, p3]`` with ``||p3[:3]|| = 1`` and ``p3 . X > 0`` for the points.
    """
    centre = xyz.mean(axis=0)
    scale = np.sqrt(3) / np.sqrt(((xyz - centre) ** 2).sum(axis=1).mean())
    t = np.eye(4)
    t[:3, :3] *= scale
    t[:3, 3] = -scale * centre
    xh = np.column_stack([xyz, np.ones(len(xyz))]) @ t.T
    mv, sv = v.mean(), 1.0 / max(v.std(), 1e-12)
    vn = (v - mv) * sv
    a = np.hstack([-xh, vn[:, None] * xh])
    _, s, vt = np.linalg.svd(a, full_matrices=False)
    if s[-2] < 1e-9 * s[0]:
        raise InputError("the raster points do not determine the projector (one plane only?)")
    p2n, p3n = vt[-1, :4], vt[-1, 4:]
    p3 = p3n @ t
    p2 = (p2n / sv + mv * p3n) @ t
    norm = np.linalg.norm(p3[:3])
    p2, p3 = p2 / norm, p3 / norm
    if np.median(np.column_stack([xyz, np.ones(len(xyz))]) @ p3) < 0:
        p2, p3 = -p2, -p3
    return np.vstack([p2, p3])


@dataclass(frozen=True, eq=False)
class ProjectorCalibration:
    """The adjusted projector with its residuals.

    Attributes
    ----------
    projector : Projector
    residuals : numpy.ndarray
        ``(N,)`` ``v`` residuals, line position minus predicted (diapositive units).
    rms : float
        Rms of ``residuals``.
    dlt_rms : float
        Rms ``v`` residual of the linear start (diapositive units): large if a plate was
        numbered wrongly.
    sigma : dict
        Standard deviations of the adjusted parameters, by name.
    """

    projector: Projector
    residuals: np.ndarray
    rms: float
    dlt_rms: float
    sigma: dict[str, float]


def _start_from_dlt(
    rows: np.ndarray, reference: Projector
) -> tuple[np.ndarray, np.ndarray, float, float]:
    p2, p3 = rows
    r3, t3 = p3[:3], p3[3]
    cy = float(p2[:3] @ r3)
    q = p2[:3] - cy * r3
    fy = float(np.linalg.norm(q))
    r2 = q / fy
    t2 = (p2[3] - cy * t3) / fy
    r1 = np.cross(r2, r3)
    rot = np.vstack([r1, r2, r3])
    # t_x is not observable from lines: keep the reference centre's position along x
    t1 = -float(reference.centre @ r1)
    return rot, np.array([t1, t2, t3]), fy, cy


def calibrate_projector(
    xyz: np.ndarray,
    v: np.ndarray,
    *,
    reference: Projector,
    distortion: Sequence[str] = ("k1",),
) -> ProjectorCalibration:
    """Fit the projector to 3-D points with the diapositive ``v`` of their raster lines.

    Parameters
    ----------
    xyz : numpy.ndarray
        ``(N, 3)`` world points on raster lines (mm), on at least two non-parallel or
        separated planes.
    v : numpy.ndarray
        ``(N,)`` diapositive ``v`` of each point's line.
    reference : Projector
        Supplies what lines cannot determine: the diapositive extent, ``c_x``, the ratio
        ``f_x / f_y`` and the centre's position along the projector's ``x`` axis.
    distortion : sequence of str
        Distortion terms to estimate (of ``k1, k2, p1, p2, k3``); the others stay 0.

    Returns
    -------
    ProjectorCalibration
    """
    unknown = sorted(set(distortion) - set(DISTORTION_TERMS))
    if unknown:
        raise InputError(f"unknown distortion terms {unknown}; choose from {DISTORTION_TERMS}")
    free_dist = [DISTORTION_TERMS.index(d) for d in DISTORTION_TERMS if d in distortion]
    xyz = np.asarray(xyz, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    if len(xyz) < 20:
        raise InputError(f"only {len(xyz)} raster points on the plates: too few for a projector")
    rows = dlt_1d(xyz, v)
    xh = np.column_stack([xyz, np.ones(len(xyz))])
    dlt_res = v - (xh @ rows[0]) / (xh @ rows[1])
    dlt_rms = float(np.sqrt(np.mean(dlt_res**2)))
    rot, t, fy, cy = _start_from_dlt(rows, reference)
    aspect = reference.K[0, 0] / reference.K[1, 1]
    cx = reference.K[0, 2]
    ref_centre = reference.centre
    rvec, _ = cv2.Rodrigues(rot)
    nd = len(free_dist)

    def build(params: np.ndarray) -> Projector:
        r, _ = cv2.Rodrigues(params[:3])
        dist = np.zeros(5)
        dist[free_dist] = params[7 : 7 + nd]
        f = params[5]
        return Projector(
            K=np.array([[f * aspect, 0.0, cx], [0.0, f, params[6]], [0.0, 0.0, 1.0]]),
            # t_x follows the rotation so the centre keeps the reference's x position exactly
            dist=dist, R=r, t=np.array([-float(ref_centre @ r[0]), params[3], params[4]]),
            width=reference.width, height=reference.height,
        )

    def residual(params: np.ndarray) -> np.ndarray:
        return v - build(params).project(xyz)[:, 1]

    start = np.concatenate([rvec.ravel(), t[1:], [fy, cy], np.zeros(nd)])
    fit = least_squares(residual, start, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12)
    if not np.all(np.isfinite(fit.fun)):
        raise InputError("projector adjustment failed: raster points behind the projector?")
    names = ("rx", "ry", "rz", "ty", "tz", "fy", "cy", *(DISTORTION_TERMS[i] for i in free_dist))
    s2 = float((fit.fun**2).sum() / max(fit.fun.size - fit.x.size, 1))
    try:
        jac = np.asarray(fit.jac)  # dense with method "lm" (the stubs allow sparse too)
        cov = np.linalg.inv(jac.T @ jac) * s2
        sigma = {nm: float(np.sqrt(max(cov[i, i], 0.0))) for i, nm in enumerate(names)}
    except np.linalg.LinAlgError:
        sigma = {nm: float("nan") for nm in names}
    return ProjectorCalibration(
        projector=build(fit.x),
        residuals=fit.fun.copy(),
        rms=float(np.sqrt(np.mean(fit.fun**2))),
        dlt_rms=dlt_rms,
        sigma=sigma,
    )
