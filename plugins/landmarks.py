"""Anatomical landmarks of the back from its curvature: VP, the lumbar dimples DL/DR, DM, SP.

After Drerup & Hierholzer (*Automatic localization of anatomical landmarks on the back
surface and construction of a body-fixed coordinate system*, J Biomech 20 (1987) 961-970):
the landmarks are regions of distinct curvature, found automatically in search regions
derived from the measured trunk:

* **VP**, the vertebra prominens (C7): the convex maximum (largest mean curvature H > 0) at
  the cervico-thoracic junction, near the trunk's centre line, where the narrow neck widens
  into the shoulders;
* **DL, DR**, the lumbar dimples over the posterior superior iliac spines: the pair of concave
  maxima (most negative H) in the lower trunk, one each side of the centre line, at about the
  same height — the patient's left dimple DL at ``-x``, the right one DR at ``+x``;
* **DM**, the skin point midway between DL and DR;
* **SP**, the sacrum point at the top of the rima ani (gluteal cleft): where, going down the
  midline from DM, the cleft's lateral concavity appears
  (:func:`~rasterserver_plugins.sacrum_point.find_sacrum_point`).

A landmark is never guessed: when the region is not measured (cropped image, holes, an arm
in front), when no candidate is distinct enough or when two candidates are too alike, it is
reported missing with a reason. Each found landmark has a confidence in [0, 1]: the product of
its *strength* (its curvature against the smallest accepted one) and its *distinctness* (how
much it exceeds the best competing candidate).

All positions are in the level frame (:mod:`rasterserver_plugins.level_frame`); the depth
of a landmark is the measured surface's (bilinear), not the smoothed fit's, which would lift a
dimple's bottom by millimetres.

The search regions and thresholds were tuned on simulated backs (presets ``normal``,
``moderate``, ``severe`` and :func:`~rasterserver.simulator.back.random_back` seeds 0-99);
seeds from 1000 on are kept for the benchmark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter, median_filter

from .curvature import Curvature
from .level_frame import LevelGrid
from .symmetry_line import curvature_features, profile_asymmetry
from .trunk import Trunk

__all__ = [
    "Landmark",
    "find_dimples",
    "find_vertebra_prominens",
    "midpoint",
]

#: Smallest mean curvature (1/mm, at the 5 mm scale) of a lumbar dimple (the simulated
#: ones reach 0.005 to 0.06; the measurement noise on a flat wall stays below 0.001).
MIN_LANDMARK_CURVATURE = 0.003
#: Smallest mean curvature (1/mm) of a vertebra prominens (0.023 to 0.04 on the simulated
#: backs).
MIN_VP_CURVATURE = 0.008
#: Least concavity (1/mm, −H) of the weaker dimple of the chosen pair. The dimples found
#: on the clinic tuning scenes (0-299, bodies and backs alone) have 0.0074/mm and more
#: (median 0.025); a pair of shallow pits above a lower back cut off by the image had 0.004.
MIN_DIMPLE_CURVATURE = 0.005
#: A runner-up this close (ratio of curvatures) to the best candidate makes the choice
#: ambiguous: the landmark is refused.
AMBIGUOUS_RATIO = 0.85
#: Range of the distance between the dimples, in units of the trunk's median half-width.
DIMPLE_DISTANCE = (0.45, 1.1)
#: Reach of the mirrored pairs (fraction of the trunk's half-width) when finding the lower
#: back's mirror axis, about which the dimples are a pair: wide enough to hold the dimples.
DIMPLE_AXIS_REACH = 0.4
#: A landmark's curvature must also exceed this many times the curvature noise that the
#: measurement noise causes (:attr:`Curvature.noise`): noisy surfaces need clearer features.
NOISE_FACTOR = 8.0
#: Concavities besides the pair, at the pair's height (within :data:`LEVEL_MM`), that make
#: the pair part of a row of concavities across the lower back: the edge of clothing (a
#: waistband standing off the skin), not two dimples. On the clinic tuning scenes a
#: waistband's edge held 5 such candidates besides the pair taken for dimples; the dimples
#: of a back have at most the furrow's point between them.
ROW_CONCAVITIES = 3
#: Height band (mm, either side of the pair's mean height) of :data:`ROW_CONCAVITIES`.
LEVEL_MM = 10.0
#: Least ratio ``κ1 / κ2`` of the principal curvatures of a dimple candidate (both negative at
#: a pit, ``κ1`` the weaker): a dimple is a pit, concave across and along the body (Drerup &
#: Hierholzer map the dimples as concave regions of positive Gaussian curvature), while a
#: clothing edge, the gluteal fold or a flank's crease is a groove, concave across it only
#: (``κ1 / κ2`` near 0 or negative, a saddle). On the clinic tuning scenes the candidates
#: within 10 mm of a true dimple had a ratio of 0.31 or more in 95 % (0.20 in 99 %), the
#: others 0.06 at the median; the grooves of waistbands made a quarter of the clinic bodies'
#: dimple pairs ambiguous.
PIT_RATIO = 0.15
#: Least ratio of the trunk's extent on the shorter side of VP to the longer one.
MIN_BALANCE = 0.4
#: A convex point at the top of the measured surface is VP's only when its curvature falls,
#: up its column and within the measured surface, below this share of its value: a maximum
#: seen on both sides, not a rise into the edge (where hair or a shadow cuts the nape off).
TOP_DROP = 0.9
#: How far (in trunk half-widths W) VP's search region reaches below the neck line. The VPs
#: found on the clinic tuning bodies lie from 0.20 W above to 0.28 W below it; the convex
#: points of the upper back that a shadowed nape let win lay 0.66-0.68 W below it (0.7 W
#: until analysis version 8).
REGION_BELOW = 0.45
#: Why a landmark next to an unmeasured cell is refused: its curvature extreme may be an
#: artefact of the one-sided fits at the hole's rim, and the true one inside the hole.
HOLE_REASON = (
    "a hole in the measured surface lies next to it (lost raster line pieces, a shadow): "
    "its position cannot be trusted"
)
#: Why DM is refused where the skin midway between the dimples is not measured.
DM_HOLE_REASON = (
    "the skin midway between the dimples is not measured (a hand, a shadow or lost raster "
    "line pieces there): DM cannot be placed"
)
#: Why the dimples are refused where the skin midway between them is not measured: the
#: lumbar spine lies there; two pits on either side of a hole (the gluteal cleft, a hand)
#: may be the buttocks' (fresh held-out clinic scene 42596).
BETWEEN_HOLE_REASON = (
    "the skin midway between the pair of concavities is not measured (a hand, a shadow or "
    "the gluteal cleft between them?): they are not to be trusted as the lumbar dimples"
)
#: Least share of a candidate's curvature window that must be measured: below it the fit
#: extrapolates over a border or a hole, where curvature extremes are artefacts.
MIN_SUPPORT = 0.6


@dataclass(frozen=True)
class Landmark:
    """A landmark found (``point`` set) or not (``reason`` set).

    Attributes
    ----------
    name : str
        ``VP``, ``DL``, ``DR``, ``DM`` or ``SP``.
    point : numpy.ndarray or None
        ``(3,)`` level-frame position (mm), None when not found.
    confidence : float
        In [0, 1]; 0 when not found.
    reason : str
        Why it was not found, or "".
    """

    name: str
    point: np.ndarray | None
    confidence: float = 0.0
    reason: str = ""

    @property
    def found(self) -> bool:
        """Whether the landmark was found."""
        return self.point is not None


def _missing(name: str, reason: str) -> Landmark:
    return Landmark(name, None, 0.0, reason)


@dataclass(frozen=True)
class _Peak:
    row: float
    col: float
    value: float


def _peaks(score: np.ndarray, region: np.ndarray, *, size: int = 5) -> list[_Peak]:
    """Local maxima of ``score`` inside ``region``, strongest first (cell positions)."""
    s = np.where(region & np.isfinite(score), score, -np.inf)
    is_peak = (s == maximum_filter(s, size=size, mode="constant", cval=-np.inf)) & np.isfinite(s)
    ii, jj = np.nonzero(is_peak)
    order = np.argsort(-s[ii, jj])
    return [_Peak(float(ii[k]), float(jj[k]), float(s[ii[k], jj[k]])) for k in order]


def _refine(score: np.ndarray, peak: _Peak, *, half: int = 2) -> tuple[float, float]:
    """Sub-cell position of a maximum: vertex of a quadric fitted to the cells around it."""
    ny, nx = score.shape
    i0, j0 = int(peak.row), int(peak.col)
    di, dj = np.mgrid[-half : half + 1, -half : half + 1]
    ii, jj = i0 + di.ravel(), j0 + dj.ravel()
    ok = (ii >= 0) & (ii < ny) & (jj >= 0) & (jj < nx)
    ii, jj, u, v = ii[ok], jj[ok], dj.ravel()[ok].astype(float), di.ravel()[ok].astype(float)
    val = score[ii, jj]
    ok = np.isfinite(val)
    if ok.sum() < 6:
        return peak.row, peak.col
    u, v, val = u[ok], v[ok], val[ok]
    a = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    c = np.linalg.lstsq(a, val, rcond=None)[0]
    hess = np.array([[2 * c[3], c[4]], [c[4], 2 * c[5]]])
    if np.linalg.det(hess) <= 0 or hess[0, 0] >= 0:
        return peak.row, peak.col  # not a proper maximum of the fit: keep the cell
    du, dv = np.linalg.solve(hess, -c[1:3])
    if abs(du) > 1.0 or abs(dv) > 1.0:
        return peak.row, peak.col
    return peak.row + float(dv), peak.col + float(du)


def _surface_point(grid: LevelGrid, curv: Curvature, row: float, col: float) -> np.ndarray:
    point = grid.point(col, row)
    if point is None:  # a cell on the border of a hole: the fitted depth is all there is
        i, j = round(row), round(col)
        point = np.array([float(grid.x_of(col)), float(grid.y_of(row)), curv.depth[i, j]])
    return point


def _measured_point(grid: LevelGrid, curv: Curvature, row: float, col: float) -> np.ndarray | None:
    """:func:`_surface_point`, or None inside a hole too wide for the curvature fit to
    bridge (the skin's depth there is unknown)."""
    point = _surface_point(grid, curv, row, col)
    return point if np.all(np.isfinite(point)) else None


def _confidence(value: float, runner_up: float, minimum: float) -> float:
    strength = min(1.0, value / (2.0 * minimum))
    distinct = min(1.0, max(0.0, 1.0 - runner_up / value) / 0.5) if value > 0 else 0.0
    return float(strength * distinct)


def _centre_cols(trunk: Trunk) -> np.ndarray:
    """The trunk's centre column in every row, filled across gaps (NaN outside the trunk)."""
    centre = trunk.centre.copy()
    rows = np.arange(centre.size)
    good = np.isfinite(centre)
    if good.any():
        inside = (rows >= trunk.top) & (rows <= trunk.bottom)
        centre[inside] = np.interp(rows[inside], rows[good], centre[good])
    return centre


def find_vertebra_prominens(
    grid: LevelGrid,
    curv: Curvature,
    trunk: Trunk,
    *,
    top_drop: float | None = TOP_DROP,
    below: float = REGION_BELOW,
) -> Landmark:
    """The vertebra prominens: the convex maximum at the cervico-thoracic junction.

    Search region (derived from the trunk, ``W`` its median half-width): rows from
    ``0.25 W`` above to ``below`` × ``W`` below the *neck line*, the first row from the top where
    the trunk is wider than ``0.6 W`` (the neck widening into the shoulders); columns within
    ``0.25 W`` of the trunk's centre line.

    Parameters
    ----------
    grid : LevelGrid
        The surface in the level frame.
    curv : Curvature
        Its curvature (at the landmark scale).
    trunk : Trunk
        The trunk found in it.
    top_drop : float or None, optional
        A candidate within 1.5 curvature scales of the measured surface's top, or beside a
        hole above it, is kept when its mean curvature falls up its column, inside the
        measured surface, below this share of its value (:data:`TOP_DROP`); None refuses
        every such candidate (analysis version 6).
    below : float, optional
        How far the search region reaches below the neck line, in ``W``
        (:data:`REGION_BELOW`; 0.7 until analysis version 8).

    Returns
    -------
    Landmark
        ``VP`` in level coordinates, or missing with a reason.
    """
    if not trunk.found:
        return _missing("VP", trunk.reason or "no trunk in the surface")
    s = grid.spacing
    w = trunk.reference_half_width()
    hw = trunk.half_width
    rows = np.arange(trunk.top, trunk.bottom + 1)
    wide = rows[hw[rows] >= 0.6 * w]
    neck = int(wide[0]) if wide.size else trunk.top
    r0 = max(trunk.top, neck - round(0.25 * w / s))
    r1 = min(trunk.bottom, neck + round(below * w / s))
    centre = _centre_cols(trunk)
    region = _band(grid.shape, centre, r0, r1, 0.0, 0.25 * w / s)
    h = curv.mean
    all_peaks = _peaks(h, region)
    minimum = max(MIN_VP_CURVATURE, NOISE_FACTOR * curv.noise)
    # When the trunk is already wide in its first profile, no neck is in view: say so.
    hint = " (no neck in view: is the image cropped at the top?)" if neck == trunk.top else ""
    if not all_peaks or all_peaks[0].value < minimum:
        return _missing("VP", "no convex point near the midline at the neck's base" + hint)
    supported = curv.support >= MIN_SUPPORT
    best = all_peaks[0]
    # where hair or a shadow ends the surface just above C7, its bump's upper flank may still
    # be measured: then the maximum is seen, not an artefact of the one-sided fit at the edge
    seen = top_drop is not None and _falls_above(grid, h, best, top_drop)
    at_top = best.row - trunk.top < 1.5 * curv.sigma / s and not seen
    if at_top or not supported[int(best.row), int(best.col)]:
        where = "top" if at_top else "border"
        return _missing(
            "VP",
            f"the strongest convex point near the neck's base lies at the {where} of the "
            "measured surface (image cropped or region not measured)",
        )
    runner = _runner_up(all_peaks, best, min_distance=15.0 / s, supported=supported)
    if runner >= AMBIGUOUS_RATIO * best.value:
        return _missing("VP", "two similar convex points near the neck's base: ambiguous" + hint)
    balance = _balance(trunk, best, 10.0 / s)
    if balance < MIN_BALANCE:
        return _missing(
            "VP",
            "the trunk is not measured on both sides of the convex point at the neck's base "
            "(the nape hidden by hair or a shadow, or half a back in view?)",
        )
    row, col = _refine(h, best)
    if _next_to_hole(grid, row, col, curv.sigma, below_only=seen):
        return _missing("VP", HOLE_REASON)
    point = _surface_point(grid, curv, row, col)
    return Landmark("VP", point, _confidence(best.value, max(runner, 0.0), minimum))


def _next_to_hole(
    grid: LevelGrid, row: float, col: float, radius: float, *, below_only: bool = False
) -> bool:
    """Whether an unmeasured cell lies within ``radius`` mm of the fractional cell (with
    ``below_only``, one in its row or below it: the surface's edge above is allowed)."""
    s = grid.spacing
    k = int(np.ceil(radius / s)) + 1
    i0, j0 = round(row), round(col)
    ii, jj = np.mgrid[i0 - k : i0 + k + 1, j0 - k : j0 + k + 1]
    near = (ii - row) ** 2 + (jj - col) ** 2 <= (radius / s) ** 2
    if below_only:
        near &= ii >= row
    ny, nx = grid.shape
    inside = (ii >= 0) & (ii < ny) & (jj >= 0) & (jj < nx)
    if not inside[near].all():
        return True
    return bool(np.isnan(grid.z[ii[near], jj[near]]).any())


def _falls_above(grid: LevelGrid, h: np.ndarray, peak: _Peak, drop: float) -> bool:
    """Whether ``h`` falls below ``drop`` times the peak's value up the peak's column before
    the measured surface ends (the maximum's upper flank is measured)."""
    j = int(peak.col)
    for i in range(int(peak.row) - 1, -1, -1):
        if not (np.isfinite(grid.z[i, j]) and np.isfinite(h[i, j])):
            return False
        if h[i, j] < drop * peak.value:
            return True
    return False


def _balance(trunk: Trunk, peak: _Peak, rows: float) -> float:
    """How evenly the trunk extends on both sides of ``peak`` (shorter / longer side)."""
    r = np.arange(int(peak.row - rows), int(peak.row + rows) + 1)
    r = r[(r >= 0) & (r < trunk.left.size)]
    a = peak.col - trunk.left[r]
    b = trunk.right[r] - peak.col
    ok = np.isfinite(a) & np.isfinite(b) & (a >= 0) & (b >= 0)
    if not ok.any():
        return 0.0
    return float(np.median(np.minimum(a[ok], b[ok]) / np.maximum(np.maximum(a[ok], b[ok]), 1)))


def _vertex(values: np.ndarray, index: int) -> float:
    """Sub-cell position of the maximum ``values[index]``: vertex of the parabola through it
    and its neighbours (the index itself at an end or when not a proper maximum)."""
    if index <= 0 or index >= values.size - 1:
        return float(index)
    a, b, c = values[index - 1], values[index], values[index + 1]
    denom = a - 2.0 * b + c
    if not (np.isfinite(denom) and denom < 0):
        return float(index)
    return float(index + np.clip(0.5 * (a - c) / denom, -0.5, 0.5))


def _runner_up(
    peaks: list[_Peak], best: _Peak, *, min_distance: float, supported: np.ndarray
) -> float:
    for p in peaks[1:]:
        if not supported[int(p.row), int(p.col)]:
            continue
        if math.hypot(p.row - best.row, p.col - best.col) >= min_distance:
            return p.value
    return 0.0


def _band(
    shape: tuple[int, int], centre: np.ndarray, r0: int, r1: int, inner: float, outer: float
) -> np.ndarray:
    """Cells of rows ``r0..r1`` whose column offset from ``centre`` lies in [inner, outer]."""
    ny, nx = shape
    rows = np.arange(ny)[:, None]
    off = np.abs(np.arange(nx)[None, :] - centre[:, None])
    with np.errstate(invalid="ignore"):
        return (rows >= r0) & (rows <= r1) & (off >= inner) & (off <= outer)


def find_dimples(
    grid: LevelGrid,
    curv: Curvature,
    trunk: Trunk,
    vp: Landmark,
    row_concavities: int = ROW_CONCAVITIES,
    *,
    pit_ratio: float | None = PIT_RATIO,
    row_each: bool = True,
) -> tuple[Landmark, Landmark]:
    """The lumbar dimples DL (patient's left, ``-x``) and DR (right, ``+x``).

    Search region: rows of the lower 45 % of the trunk between VP (or the trunk's top) and
    the trunk's bottom, columns within ``0.8 W`` of the centre line. The concave maxima
    (most negative H) found there that are pits (:data:`PIT_RATIO`) are paired: a pair must
    be roughly level (height difference at most 30 % of their distance), centred (midpoint
    within ``0.3 W`` of the centre line), :data:`DIMPLE_DISTANCE` apart (which keeps the
    midline furrow, a string of concave points, out of the pairs) and of comparable depth
    (the weaker at least a quarter of the stronger); the pair with the largest summed
    concavity wins, unless another pair comes within :data:`AMBIGUOUS_RATIO` of it. The
    winner is refused where the skin midway between its dimples, DM's place, is not
    measured (:data:`BETWEEN_HOLE_REASON`): a pair across a hole is not to be trusted, and
    dropping it for the next pair could unmask a wrong one.

    Parameters
    ----------
    grid : LevelGrid
        The surface in the level frame.
    curv : Curvature
        Its curvature.
    trunk : Trunk
        The trunk.
    vp : Landmark
        The vertebra prominens (its height starts the search), found or not.
    row_concavities : int, optional
        Refuse the pair when this many other candidates lie at its height (a row of
        concavities: a clothing edge); 0 does not check (version 4). ``row_each``: at
        either dimple's height (version 11), not at the pair's mean height.
    pit_ratio : float or None, optional
        Least ratio of the weaker to the stronger principal curvature of a candidate
        (:data:`PIT_RATIO`): grooves are no dimples. None does not check (version 5).

    Returns
    -------
    tuple of Landmark
        ``DL`` and ``DR``.
    """
    if not trunk.found:
        reason = trunk.reason or "no trunk in the surface"
        return _missing("DL", reason), _missing("DR", reason)
    s = grid.spacing
    w = trunk.reference_half_width()
    top = float(grid.row_of(vp.point[1])) if vp.point is not None else float(trunk.top)
    r0 = round(top + 0.55 * (trunk.bottom - top))
    r1 = trunk.bottom
    centre = _centre_cols(trunk)
    concave = -curv.mean
    supported = curv.support >= MIN_SUPPORT
    region = _band(grid.shape, centre, r0, r1, 0.0, 0.8 * w / s)
    minimum = max(MIN_LANDMARK_CURVATURE, NOISE_FACTOR * curv.noise)
    candidates = [
        p
        for p in _peaks(concave, region)
        if p.value >= minimum and supported[int(p.row), int(p.col)]
    ]
    pits = [p for p in candidates if pit_ratio is None or _is_pit(curv, p, pit_ratio)]
    grooves = len(candidates) - len(pits)
    peaks = pits[:16]
    axis = _local_axes(curv, centre, r0, r1, w / s)
    pairs = []
    for pl in peaks:
        for pr in peaks:
            dx = (pr.col - pl.col) * s
            if dx <= 0:
                continue
            dy = (pr.row - pl.row) * s
            mid_row = round(0.5 * (pl.row + pr.row))
            mid_off = (0.5 * (pl.col + pr.col) - axis[mid_row]) * s
            weak, strong = sorted((pl.value, pr.value))
            if (
                DIMPLE_DISTANCE[0] * w <= dx <= DIMPLE_DISTANCE[1] * w
                and abs(dy) <= 0.3 * dx
                and abs(mid_off) <= 0.1 * dx
                and weak >= strong / 4.0
            ):
                pairs.append((pl.value + pr.value, pl, pr))
    # Where the measured trunk ends tells whether the lower back can be in view at all.
    extent = (trunk.bottom - top) * s
    hint = f" (the measured trunk ends {extent:.0f} mm below {'VP' if vp.found else 'its top'})"
    if not pairs:
        if not peaks and not grooves:
            reason = "no concavity in the lower back (dimples not in view, covered or not measured)"
        elif not peaks:
            reason = "no pit in the lower back: its concavities are grooves (clothing, folds?)"
        else:
            reason = "no level, symmetric pair of concavities in the lower back"
        side = _less_measured_side(grid, trunk, axis, r0, r1, w / s)
        if side:
            reason += f"; the {side} side of the lower back is not fully measured (covered?)"
        reason += hint
        return _missing("DL", reason), _missing("DR", reason)
    pairs.sort(key=lambda p: -p[0])
    score, pl, pr = pairs[0]
    runner = 0.0
    for other_score, ql, qr in pairs[1:]:
        moved = max(
            math.hypot(ql.row - pl.row, ql.col - pl.col),
            math.hypot(qr.row - pr.row, qr.col - pr.col),
        )
        if moved * s >= 15.0:
            runner = other_score
            break
    if runner >= AMBIGUOUS_RATIO * score:
        reason = "two similar pairs of concavities in the lower back: ambiguous" + hint
        return _missing("DL", reason), _missing("DR", reason)
    # every concavity counts, grooves too: a waistband's edge is mostly grooves, and the one
    # or two pits among them made a pair (version 10; version 6 counted the pits only); at
    # either dimple's height, as one pit of a waistband's edge paired with a true dimple
    # 20 mm above it and the pair's mean height missed the row (version 11)
    levels = (pl.row, pr.row) if row_each else (0.5 * (pl.row + pr.row),)
    others = [q for q in candidates if q is not pl and q is not pr]
    beside = max(sum(abs(q.row - lv) * s <= LEVEL_MM for q in others) for lv in levels)
    if row_concavities > 0 and beside >= row_concavities:
        reason = (
            f"the pair lies in a row of {beside + 2} concavities across the lower back (the "
            "edge of clothing, not dimples?)"
        )
        return _missing("DL", reason), _missing("DR", reason)
    if min(pl.value, pr.value) < MIN_DIMPLE_CURVATURE:
        reason = (
            "the best pair of concavities in the lower back is too shallow to be the dimples "
            f"(weaker {min(pl.value, pr.value):.4f}/mm, at least {MIN_DIMPLE_CURVATURE}/mm): "
            "dimples not in view, covered or not measured?" + hint
        )
        return _missing("DL", reason), _missing("DR", reason)
    below = (trunk.bottom - max(pl.row, pr.row)) * s
    if below < 2.0 * curv.sigma:
        reason = "the dimples lie at the bottom edge of the measured surface (image cropped)"
        return _missing("DL", reason), _missing("DR", reason)
    refined = [_refine(concave, peak) for peak in (pl, pr)]
    if any(_next_to_hole(grid, row, col, curv.sigma) for row, col in refined):
        return _missing("DL", HOLE_REASON), _missing("DR", HOLE_REASON)
    (row_l, col_l), (row_r, col_r) = refined
    if _measured_point(grid, curv, 0.5 * (row_l + row_r), 0.5 * (col_l + col_r)) is None:
        return _missing("DL", BETWEEN_HOLE_REASON), _missing("DR", BETWEEN_HOLE_REASON)
    out = []
    for name, peak, (row, col) in zip(("DL", "DR"), (pl, pr), refined, strict=True):
        point = _surface_point(grid, curv, row, col)
        conf = _confidence(score, runner, 2 * minimum) * min(1.0, peak.value / (2.0 * minimum))
        out.append(Landmark(name, point, conf))
    return out[0], out[1]


def _is_pit(curv: Curvature, peak: _Peak, ratio: float) -> bool:
    """Whether the concave candidate is a pit: ``κ1 <= ratio κ2`` (both concave, ``κ2 < 0``),
    not a groove (``κ1`` near 0) or a saddle (``κ1 > 0``)."""
    i, j = int(peak.row), int(peak.col)
    k1, k2 = float(curv.k1[i, j]), float(curv.k2[i, j])
    return k2 < 0.0 and k1 <= ratio * k2


def _less_measured_side(
    grid: LevelGrid, trunk: Trunk, axis: np.ndarray, r0: int, r1: int, reach: float
) -> str:
    """``"left"`` or ``"right"`` when that side of the lower back (rows ``r0..r1``, from
    ``0.2`` to ``0.8 reach`` columns off the axis) has under 80 % of the other's measured
    cells; "" otherwise."""
    nx = grid.shape[1]
    rows = np.arange(r0, r1 + 1)
    off = np.arange(nx)[None, :] - axis[rows][:, None]
    measured = np.isfinite(grid.z[rows])
    with np.errstate(invalid="ignore"):
        band = (np.abs(off) >= 0.2 * reach) & (np.abs(off) <= 0.8 * reach)
        left = int((measured & band & (off < 0)).sum())
        right = int((measured & band & (off > 0)).sum())
    if left < 0.8 * right:
        return "left"
    if right < 0.8 * left:
        return "right"
    return ""


def _local_axes(curv: Curvature, centre: np.ndarray, r0: int, r1: int, reach: float) -> np.ndarray:
    """Column of the mirror axis of every row ``r0..r1`` (NaN elsewhere).

    The axis minimising the curvature asymmetry of the row (as for the symmetry line, see
    :func:`rasterserver_plugins.symmetry_line.profile_asymmetry`) within ``0.6 reach``
    columns of the trunk's centre, median-filtered over 7 rows: the midline of the lower
    back, about which the dimples are a mirror pair.
    """
    rows = np.arange(r0, r1 + 1)
    out = np.full(centre.size, np.nan)
    table = profile_asymmetry(
        curvature_features(curv, rows), reach=max(2, round(2 * DIMPLE_AXIS_REACH * reach))
    )
    k = np.arange(table.shape[1])[None, :] / 2.0
    near = np.abs(k - centre[rows][:, None]) <= 0.6 * reach
    cost = np.where(near & np.isfinite(table), table, np.inf)
    best = np.argmin(cost, axis=1) / 2.0
    best = np.where(np.isfinite(cost.min(axis=1)), best, centre[rows])
    out[rows] = median_filter(best, size=7, mode="nearest")
    return out


def midpoint(grid: LevelGrid, curv: Curvature, dl: Landmark, dr: Landmark) -> Landmark:
    """DM: the point of the skin midway between the dimples (found when both are).

    The midpoint of DL and DR lies inside the body when the back is curved across; DM is
    the surface point at the same horizontal position (the measured depth there), a skin
    landmark like VP.
    """
    if dl.point is None or dr.point is None:
        return _missing("DM", "needs both lumbar dimples")
    mid = 0.5 * (dl.point + dr.point)
    row, col = float(grid.row_of(mid[1])), float(grid.col_of(mid[0]))
    point = _measured_point(grid, curv, row, col)
    if point is None:
        return _missing("DM", DM_HOLE_REASON)
    return Landmark("DM", point, min(dl.confidence, dr.confidence))


def carried_landmark(grid: LevelGrid, curv: Curvature, point: np.ndarray) -> Landmark:
    """VP carried from another visit (``point``, level mm): on this surface where it is
    measured there (its depth is read), as carried where hair or a shadow hides it."""
    row, col = float(grid.row_of(point[1])), float(grid.col_of(point[0]))
    inside = 0 <= round(row) < grid.shape[0] and 0 <= round(col) < grid.shape[1]
    measured = _measured_point(grid, curv, row, col) if inside else None
    return Landmark("VP", point.copy() if measured is None else measured, 0.5)
