"""The clinical parameters of a back, from its landmarks, symmetry line and spinal midline.

The parameter set is DIERS formetric's, as tabulated by Degenhardt et al. (*Appraisal of the
DIERS method for calculating postural measurements: an observational study*, Scoliosis
Spinal Disord 12 (2017) 28, Table 1), with the sagittal-profile construction of Drerup &
Hierholzer (inflection points ICT, ITL, ILS and the apices KA, LA of the symmetry line's
sagittal profile) and, for the asymmetry, the mirror comparison of Komeili et al. (*Surface
topography asymmetry maps categorizing external deformity in scoliosis*, Spine J 14 (2014)
973-983; Spine J 15 (2015) 743-751).

Everything is computed in the level frame (:mod:`rasterserver_plugins.level_frame`: ``x'``
to the patient's right, ``y'`` down along gravity, ``z'`` the station's horizontal sagittal
direction, anterior), so "vertical", "horizontal", "height" refer to gravity. The
definitions and signs match ``docs/analysis.md`` (and the simulator's truth,
``docs/simulator_truth.md``, which the benchmark compares against):

* trunk length: ``|VP − DM|``;
* trunk inclination: ``VP.z − DM.z`` (mm) and ``atan2(VP.z − DM.z, DM.y − VP.y)`` (deg), + when
  the upper trunk leans forwards;
* trunk imbalance: ``VP.x − DM.x`` (mm) and ``atan2(VP.x − DM.x, DM.y − VP.y)`` (deg), + when
  VP lies to the right of DM;
* pelvic tilt: ``DL.y − DR.y`` (mm) and ``atan2(DL.y − DR.y, DR.x − DL.x)`` (deg), + when the
  right dimple is higher;
* pelvic torsion: the upward tilt ``atan2(−n_y, −n_z)`` of the outward surface normal at DR
  minus the one at DL (deg; + when the right dimple's surface faces more upwards);
* pelvic rotation: ``atan2(DL.z − DR.z, DR.x − DL.x)`` (deg; + right dimple backwards);
* kyphotic angle: inclination at ITL − inclination at ICT; lordotic angle: inclination at
  ITL − inclination at ILS (deg), the inclination of the sagittal profile being its tangent's
  angle from the vertical, ``atan2(dz, dy)``;
* flèche cervicale ``VP.z − KA.z`` and flèche lombaire ``LA.z − KA.z`` (mm): horizontal
  distances from the plumb line through the kyphosis apex;
* surface rotation rms, signed maximum, largest (≥ 0) and smallest (≤ 0) value (deg);
* lateral deviation of the midline from the line VP–DM in the frontal plane: rms, signed
  maximum, largest (≥ 0), smallest (≤ 0) (mm);
* scoliosis angle (deg): Cobb-like, the largest change of the frontal midline's tangent
  between consecutive extremes of that tangent (its inflection points) or its ends;
* asymmetry rms (mm): the trunk between VP and DM against its mirror image about the body's
  symmetry plane (through DM, normal to the transverse axis DL–DR made perpendicular to
  VP–DM): rms of the depth difference ``z'(p) − z'(mirror of the mirrored surface)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .curvature import fit_quadric_at
from .level_frame import LevelGrid, bilinear
from .spinal_midline import SpinalMidline
from .symmetry_line import SymmetryLine
from .trunk import Trunk

__all__ = [
    "PARAMETER_UNITS",
    "SAGITTAL_POINTS",
    "SagittalProfile",
    "cobb_angle",
    "sagittal_profile",
    "signed_extremes",
    "undecided_sign",
]

#: Unit of every parameter, in the order they are reported.
PARAMETER_UNITS: dict[str, str] = {
    "trunk_length": "mm",
    "trunk_inclination_mm": "mm",
    "trunk_inclination_deg": "deg",
    "trunk_imbalance_mm": "mm",
    "trunk_imbalance_deg": "deg",
    "pelvic_tilt_mm": "mm",
    "pelvic_tilt_deg": "deg",
    "pelvic_torsion_deg": "deg",
    "pelvic_rotation_deg": "deg",
    "kyphotic_angle_deg": "deg",
    "lordotic_angle_deg": "deg",
    "fleche_cervicale_mm": "mm",
    "fleche_lombaire_mm": "mm",
    "surface_rotation_rms_deg": "deg",
    "surface_rotation_max_deg": "deg",
    "surface_rotation_pos_max_deg": "deg",
    "surface_rotation_neg_max_deg": "deg",
    "lateral_deviation_rms_mm": "mm",
    "lateral_deviation_max_mm": "mm",
    "lateral_deviation_pos_max_mm": "mm",
    "lateral_deviation_neg_max_mm": "mm",
    "scoliosis_angle_deg": "deg",
    "asymmetry_rms_mm": "mm",
}

#: The points of the sagittal profile, top to bottom.
SAGITTAL_POINTS: tuple[str, ...] = ("ICT", "KA", "ITL", "LA", "ILS")

#: Heights (fractions of VP–DM) where ITL is looked for: clear of VP's bump and the sacrum.
ITL_SEARCH = (0.15, 0.95)
#: Savitzky–Golay window (mm) of the sagittal profile's tangent (cubic fit).
PROFILE_WINDOW = 33.0
#: Savitzky–Golay window (mm) of the frontal midline's tangent (cubic fit).
FRONTAL_WINDOW = 45.0
#: Extremes of the frontal tangent closer than this (deg) are noise, not a curve.
COBB_TOLERANCE = 1.0
#: How far apart (mm, deg) the largest deviation (rotation) to each side must be for the
#: signed maximum to be reported: 1.96 x sqrt(2) x the repeatability SD of the one-sided
#: maxima (0.54 mm, 0.51 deg; ``rasterserver.trends.REPEATABILITY_SD``). Closer, the sign of
#: the largest is the measurement's noise (a double curve of +18.4 / -18.2 mm was measured
#: +17.4 / -17.9 mm: "max" -17.9 against a truth of +18.4), and comparing visits would read a
#: flip of sign as a change of twice the curve.
SIGN_MARGIN = {"lateral_deviation_max_mm": 1.5, "surface_rotation_max_deg": 1.4}
#: Least share of the symmetry line's levels (VP to DM) where the spinal midline is measured
#: (:data:`rasterserver_plugins.spinal_midline.MIN_SUPPORT`) for the midline's parameters:
#: with less, their extremes may lie where it is not.
MIDLINE_MIN_MEASURED = 0.8
#: Gaussian scale (mm) of the fit giving the surface normal at a dimple (wider than the
#: dimple, so the normal is the surrounding surface's, not the dimple's wall's).
DIMPLE_NORMAL_SCALE = 8.0


@dataclass(frozen=True)
class SagittalProfile:
    """The symmetry line's sagittal profile and its construction points.

    Attributes
    ----------
    y, z : numpy.ndarray
        ``(N,)`` level height and depth of the profile (mm), extended beyond VP and DM.
    inclination : numpy.ndarray
        ``(N,)`` angle (deg) of the tangent from the vertical, + running anteriorly going
        down.
    t : numpy.ndarray
        ``(N,)`` height fraction (0 at VP, 1 at DM).
    points : dict of str to int
        Index of ``ICT``, ``KA``, ``ITL``, ``LA``, ``ILS`` (see :func:`sagittal_profile`).
    """

    y: np.ndarray
    z: np.ndarray
    inclination: np.ndarray
    t: np.ndarray
    points: dict[str, int] = field(default_factory=dict)


def signed_extremes(values: np.ndarray) -> tuple[float, float, float, float]:
    """The rms, the value of largest magnitude (signed), the largest (≥ 0) and smallest (≤ 0).

    As DIERS reports them: ``+max`` of a curve that never crosses to the positive side is 0.
    """
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return (math.nan,) * 4
    return (
        float(np.sqrt(np.mean(v * v))),
        float(v[np.argmax(np.abs(v))]),
        max(float(v.max()), 0.0),
        min(float(v.min()), 0.0),
    )


def undecided_sign(extremes: tuple[float, float, float, float], margin: float, unit: str) -> str:
    """Why the signed maximum of :func:`signed_extremes` is refused, or "" when it is not.

    Parameters
    ----------
    extremes : tuple of float
        ``(rms, max, pos_max, neg_max)`` from :func:`signed_extremes`.
    margin : float
        The difference between the two sides' magnitudes below which the sign of the larger
        is not decided by the measurement.
    unit : str
        For the message.

    Returns
    -------
    str
        The reason, or "" when the larger side exceeds the other by ``margin`` or more.
    """
    _rms, _peak, pos, neg = extremes
    if not (math.isfinite(pos) and math.isfinite(neg)) or abs(pos + neg) >= margin:
        return ""
    return (
        f"the largest values to either side ({pos:+.1f} and {neg:+.1f} {unit}) are within "
        f"{margin:g} {unit} of each other: which is larger, and so the sign, is not decided "
        "by the measurement; see the positive and negative maxima"
    )


def _turning_points(values: np.ndarray, tolerance: float) -> list[int]:
    """First index and the alternating extremes after it (excursions above ``tolerance``)."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return []
    points = [0]
    direction, extreme = 0, 0
    for i in range(1, v.size):
        if direction == 0:
            if abs(v[i] - v[0]) > tolerance:
                direction, extreme = (1 if v[i] > v[0] else -1), i
        elif direction * (v[i] - v[extreme]) >= 0.0:
            extreme = i
        elif direction * (v[extreme] - v[i]) > tolerance:
            points.append(extreme)
            direction, extreme = -direction, i
    if direction != 0:
        points.append(extreme)
    return points


def _tangent_angle(along: np.ndarray, across: np.ndarray, window: float, step: float) -> np.ndarray:
    """Angle (deg) of a sampled line's tangent from ``along``: a cubic Savitzky–Golay slope."""
    n = along.size
    win = round(window / step) | 1
    win = min(win, n if n % 2 else n - 1)
    if win < 5:
        return np.degrees(np.arctan2(np.gradient(across), np.gradient(along)))
    # imported here: scipy.signal costs ~0.7 s, paid by every command that lists the stages
    from scipy.signal import savgol_filter

    d_across = savgol_filter(across, win, 3, deriv=1, mode="interp")
    d_along = savgol_filter(along, win, 3, deriv=1, mode="interp")
    return np.degrees(np.arctan2(d_across, d_along))


def cobb_angle(vertical: np.ndarray, lateral: np.ndarray, step: float) -> float:
    """Cobb-like angle (deg) of a line in the frontal plane.

    The tangent's angle from the vertical (``atan2(dx, dy)``, cubic Savitzky–Golay slope over
    :data:`FRONTAL_WINDOW`) is taken at its first sample and at its alternating extremes
    (the line's inflection points, excursions above :data:`COBB_TOLERANCE`); one curve lies
    between two consecutive ones, and its angle is the difference of the tangents there, as the
    Cobb angle is the angle between the end vertebrae most tilted into a curve. The result is
    the largest (0 for a straight line).

    Only tangents with a centred window are read: within half a window of the line's ends the
    fit extrapolates its slope, several times noisier (a straight back read 4.3° from the
    tangent at its last sample alone). A curve's end vertebrae lie farther than that from VP
    and DM. Where the line has gaps (NaN samples, levels whose midline is refused), each
    measured piece is read so, and pieces too short for a centred tangent are left out;
    NaN when nothing is left.
    """
    edge = round(FRONTAL_WINDOW / step) // 2
    ok = np.isfinite(vertical) & np.isfinite(lateral)
    runs = _runs(ok)
    betas = []
    for lo, hi in runs:
        if hi - lo < 5:  # no tangent worth reading (a lone sample has none at all)
            continue
        beta = _tangent_angle(vertical[lo:hi], lateral[lo:hi], FRONTAL_WINDOW, step)
        if beta.size > 2 * edge + 4:
            betas.append(beta[edge : beta.size - edge])
        elif len(runs) == 1:
            betas.append(beta)
    if not betas:
        return math.nan
    beta = np.concatenate(betas)
    tp = _turning_points(beta, COBB_TOLERANCE)
    if len(tp) < 2:
        return 0.0
    return float(np.abs(np.diff(beta[tp])).max())


def _runs(ok: np.ndarray) -> list[tuple[int, int]]:
    """``(start, stop)`` of each run of True in ``ok``."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def sagittal_profile(
    grid: LevelGrid, line: SymmetryLine, vp: np.ndarray, dm: np.ndarray
) -> SagittalProfile | None:
    """The sagittal profile of the symmetry line, with ICT, KA, ITL, LA and ILS.

    The profile is the measured depth along the symmetry line, continued up to
    :data:`PROFILE_WINDOW` / 2 above VP and below DM (straight down from the line's ends) so the
    tangents there are centred. Its inclination is the angle of the tangent (cubic
    Savitzky–Golay slope over :data:`PROFILE_WINDOW`) from the vertical. Then:

    * ITL: the maximum of the inclination for heights ``t`` in :data:`ITL_SEARCH`;
    * ICT: its minimum between VP and ITL; ILS: its minimum between ITL and DM;
    * KA: the most posterior point (smallest ``z'``) between ICT and ITL; LA: the most
      anterior one (largest ``z'``) between ITL and ILS.

    Returns
    -------
    SagittalProfile or None
        None when the profile does not cover the ITL search range.
    """
    s = grid.spacing
    extra = round(0.5 * PROFILE_WINDOW / s)
    r_top = float(grid.row_of(line.y[0]))
    rows_up = r_top - np.arange(extra, 0, -1)
    rows_down = float(grid.row_of(line.y[-1])) + np.arange(1, extra + 1)
    rows = np.concatenate([rows_up, grid.row_of(line.y), rows_down])
    xs = np.concatenate([np.full(extra, line.x[0]), line.x, np.full(extra, line.x[-1])])
    z = bilinear(grid.z, grid.col_of(xs), rows)
    z[extra : extra + line.z.size] = line.z
    y = grid.y_of(rows)
    ok = np.isfinite(z)
    # Keep the line and the measured continuation next to it at both ends.
    lo = extra
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    hi = extra + line.z.size
    while hi < z.size and ok[hi]:
        hi += 1
    y, z = y[lo:hi], z[lo:hi]
    if np.isnan(z).any():
        good = np.isfinite(z)
        z = np.interp(y, y[good], z[good])
    t = (y - vp[1]) / (dm[1] - vp[1])
    alpha = _tangent_angle(y, z, PROFILE_WINDOW, s)
    eps = 1e-9
    inside = np.flatnonzero((t >= -eps) & (t <= 1.0 + eps))
    search = np.flatnonzero((t >= ITL_SEARCH[0]) & (t <= ITL_SEARCH[1]))
    if inside.size < 3 or search.size == 0:
        return None
    itl = int(search[np.argmax(alpha[search])])
    above = inside[inside <= itl]
    below = inside[inside >= itl]
    ict = int(above[np.argmin(alpha[above])])
    ils = int(below[np.argmin(alpha[below])])
    ka = ict + int(np.argmin(z[ict : itl + 1]))
    la = itl + int(np.argmax(z[itl : ils + 1]))
    return SagittalProfile(
        y=y,
        z=z,
        inclination=alpha,
        t=t,
        points={"ICT": ict, "KA": ka, "ITL": itl, "LA": la, "ILS": ils},
    )


def _upward_tilt(grid: LevelGrid, point: np.ndarray) -> float:
    """Upward tilt (deg) of the outward surface normal at ``point``: ``atan2(-n_y, -n_z)``."""
    coef = fit_quadric_at(
        grid.z,
        grid.spacing,
        grid.col_of(np.array([point[0]])),
        grid.row_of(np.array([point[1]])),
        (DIMPLE_NORMAL_SCALE, DIMPLE_NORMAL_SCALE),
    )[0]
    zy = coef[2]
    # the outward normal is (z_x, z_y, -1) / W, so atan2(-n_y, -n_z) = atan2(-z_y, 1)
    return math.degrees(math.atan2(-zy, 1.0)) if np.isfinite(zy) else math.nan


def asymmetry_rms(
    grid: LevelGrid, trunk: Trunk, vp: np.ndarray, dm: np.ndarray, transverse: np.ndarray
) -> float:
    """Rms (mm) of the trunk between VP and DM against its mirror image.

    The mirror plane passes through DM with normal ``transverse`` (the body frame's
    transverse axis, level frame). Each measured trunk cell ``p`` is mirrored to ``p'``;
    where the surface is measured below ``p'`` (same ``x', y'``) the residual is the depth
    difference ``z'(p') − z'_surface(x'(p'), y'(p'))``.
    """
    r0 = max(trunk.top, int(np.ceil(float(grid.row_of(vp[1])))))
    r1 = min(trunk.bottom, int(np.floor(float(grid.row_of(dm[1])))))
    if r1 <= r0:
        return math.nan
    ii, jj = np.nonzero(trunk.mask[r0 : r1 + 1])
    ii = ii + r0
    p = np.column_stack([grid.x_of(jj), grid.y_of(ii), grid.z[ii, jj]])
    n = np.asarray(transverse, dtype=float)
    n = n / np.linalg.norm(n)
    q = p - 2.0 * ((p - dm) @ n)[:, None] * n[None, :]
    zq = bilinear(grid.z, grid.col_of(q[:, 0]), grid.row_of(q[:, 1]))
    inside = trunk.mask[
        np.clip(np.rint(grid.row_of(q[:, 1])).astype(int), 0, grid.shape[0] - 1),
        np.clip(np.rint(grid.col_of(q[:, 0])).astype(int), 0, grid.shape[1] - 1),
    ]
    res = (q[:, 2] - zq)[inside & np.isfinite(zq)]
    if res.size < 0.25 * p.shape[0] or res.size == 0:
        return math.nan
    return float(np.sqrt(np.mean(res * res)))


def back_parameters(
    grid: LevelGrid,
    trunk: Trunk,
    landmarks: dict[str, np.ndarray | None],
    line: SymmetryLine | None,
    midline: SpinalMidline | None,
    transverse: np.ndarray | None,
) -> tuple[dict[str, float], dict[str, np.ndarray], dict[str, str]]:
    """Every parameter that the found landmarks and lines allow.

    Parameters
    ----------
    grid : LevelGrid
        The surface in the level frame.
    trunk : Trunk
        The trunk.
    landmarks : dict of str to numpy.ndarray or None
        Level points of ``VP``, ``DL``, ``DR``, ``DM`` (None when not found).
    line : SymmetryLine or None
        The symmetry line (None when not found).
    midline : SpinalMidline or None
        Surface rotation and midline (None when not found).
    transverse : numpy.ndarray or None
        The body frame's transverse axis (level frame).

    Returns
    -------
    values : dict of str to float
        Parameter values (see :data:`PARAMETER_UNITS`), only those computed.
    points : dict of str to numpy.ndarray
        Level points of the sagittal profile's ``ICT``, ``KA``, ``ITL``, ``LA``, ``ILS``.
    reasons : dict of str to str
        Why each missing parameter is missing.
    """
    vp, dl, dr, dm = (landmarks.get(k) for k in ("VP", "DL", "DR", "DM"))
    out: dict[str, float] = {}
    reasons: dict[str, str] = {}
    points: dict[str, np.ndarray] = {}

    def missing(names: list[str], why: str) -> None:
        for name in names:
            reasons[name] = why

    trunk_names = [
        "trunk_length",
        "trunk_inclination_mm",
        "trunk_inclination_deg",
        "trunk_imbalance_mm",
        "trunk_imbalance_deg",
    ]
    if vp is not None and dm is not None:
        height = float(dm[1] - vp[1])
        out["trunk_length"] = float(np.linalg.norm(vp - dm))
        out["trunk_inclination_mm"] = float(vp[2] - dm[2])
        out["trunk_inclination_deg"] = math.degrees(math.atan2(vp[2] - dm[2], height))
        out["trunk_imbalance_mm"] = float(vp[0] - dm[0])
        out["trunk_imbalance_deg"] = math.degrees(math.atan2(vp[0] - dm[0], height))
    else:
        missing(trunk_names, "needs VP and DM")
    pelvis = ["pelvic_tilt_mm", "pelvic_tilt_deg", "pelvic_torsion_deg", "pelvic_rotation_deg"]
    if dl is not None and dr is not None:
        out["pelvic_tilt_mm"] = float(dl[1] - dr[1])
        out["pelvic_tilt_deg"] = math.degrees(math.atan2(dl[1] - dr[1], dr[0] - dl[0]))
        torsion = _upward_tilt(grid, dr) - _upward_tilt(grid, dl)
        if math.isfinite(torsion):
            out["pelvic_torsion_deg"] = torsion
        else:
            reasons["pelvic_torsion_deg"] = "the surface around a dimple is not measured"
        out["pelvic_rotation_deg"] = math.degrees(math.atan2(dl[2] - dr[2], dr[0] - dl[0]))
    else:
        missing(pelvis, "needs both lumbar dimples")
    sagittal = [
        "kyphotic_angle_deg",
        "lordotic_angle_deg",
        "fleche_cervicale_mm",
        "fleche_lombaire_mm",
    ]
    profile = None
    if line is not None and vp is not None and dm is not None:
        profile = sagittal_profile(grid, line, vp, dm)
    if profile is None or line is None or vp is None:  # (line and vp: for the type checker)
        missing(sagittal, "needs the symmetry line from VP to DM")
    else:
        a, idx = profile.inclination, profile.points
        out["kyphotic_angle_deg"] = float(a[idx["ITL"]] - a[idx["ICT"]])
        out["lordotic_angle_deg"] = float(a[idx["ITL"]] - a[idx["ILS"]])
        out["fleche_cervicale_mm"] = float(vp[2] - profile.z[idx["KA"]])
        out["fleche_lombaire_mm"] = float(profile.z[idx["LA"]] - profile.z[idx["KA"]])
        xs = np.interp(profile.y, line.y, line.x)
        for name in SAGITTAL_POINTS:
            k = idx[name]
            points[name] = np.array([xs[k], profile.y[k], profile.z[k]])
    rotation = ["surface_rotation_rms_deg", "surface_rotation_max_deg"]
    rotation += ["surface_rotation_pos_max_deg", "surface_rotation_neg_max_deg"]
    deviation = ["lateral_deviation_rms_mm", "lateral_deviation_max_mm"]
    deviation += ["lateral_deviation_pos_max_mm", "lateral_deviation_neg_max_mm"]
    measured = 0.0 if midline is None else float(np.isfinite(midline.rotation).mean())
    if midline is None:
        missing([*rotation, *deviation, "scoliosis_angle_deg"], "needs the symmetry line")
    elif measured < MIDLINE_MIN_MEASURED:
        missing(
            [*rotation, *deviation, "scoliosis_angle_deg"],
            f"the spinal midline is measured over {100 * measured:.0f} % of VP-DM only (less "
            f"than {100 * MIDLINE_MIN_MEASURED:.0f} %: too little surface beside the symmetry "
            "line); its extremes may lie where it is not measured",
        )
    else:
        for names, values in ((rotation, midline.rotation), (deviation, midline.lateral_deviation)):
            extremes = signed_extremes(values)
            out.update(zip(names, extremes, strict=True))
            why = undecided_sign(extremes, SIGN_MARGIN[names[1]], PARAMETER_UNITS[names[1]])
            if why:
                del out[names[1]]
                reasons[names[1]] = why
        angle = cobb_angle(midline.points[:, 1], midline.points[:, 0], grid.spacing)
        if math.isfinite(angle):
            out["scoliosis_angle_deg"] = angle
        else:
            reasons["scoliosis_angle_deg"] = "no piece of the midline is long enough for a tangent"
    if vp is not None and dm is not None and transverse is not None:
        value = asymmetry_rms(grid, trunk, vp, dm, transverse)
        if math.isfinite(value):
            out["asymmetry_rms_mm"] = value
        else:
            reasons["asymmetry_rms_mm"] = "too little of the trunk is measured on both sides"
    else:
        reasons["asymmetry_rms_mm"] = "needs VP, DL, DR and DM (the body frame)"
    return out, points, reasons
