"""The vertebra prominens checked against the back's symmetry axis just below it, and DM.

C7's spinous process lies on the spine, and a few centimetres below it the back is mirror
symmetric about the spine: Hierholzer's symmetry line starts there. The convex maximum that
:func:`~rasterserver_plugins.landmarks.find_vertebra_prominens` takes for VP is searched
beside the measured trunk's centre line; on what a clinic's camera sees the centre line can
be pulled off the spine at the top of the back, where hair or the head's shadow hides the
nape, or a hanging arm joins the shoulder in the measured surface, and the strongest convex
point there is a shoulder's, 4-13 cm from C7 (16 of 300 clinic tuning scenes,
``benchmarks/clinic_analysis.py``).

The check runs the symmetry line's search
(:func:`~rasterserver_plugins.symmetry_line.find_symmetry_line`) from the candidate straight
down (the line's prior is vertical there) and measures how far the symmetry axis lies from
the candidate over the profiles :data:`NEAR` below it. The shoulders' points of the clinic
tuning scenes lay 23-87 mm off it; no VP within 20 mm of the truth lay beyond
:data:`MAX_OFFSET` (none refused on those 300 scenes, nor on the 203 backs of
``benchmarks/analysis.py``). A candidate beyond :data:`MAX_OFFSET` is refused; a candidate
whose axis cannot be measured there is kept (the check then says nothing either way).

Where the axis just below follows the pulled centre line (held-out clinic scene 41394: a
scapula's point 99 mm from C7, 12 mm from that axis), :func:`check_imbalance` refuses a
candidate farther beside DM than a trunk imbalance (:data:`MAX_IMBALANCE`).
"""

from __future__ import annotations

import numpy as np

from .curvature import Curvature
from .landmarks import Landmark
from .level_frame import LevelGrid
from .symmetry_line import find_symmetry_line

__all__ = [
    "MAX_IMBALANCE",
    "MAX_OFFSET",
    "NEAR",
    "axis_offset",
    "check_confidence",
    "check_imbalance",
    "check_vertebra_prominens",
]

#: Heights below VP (mm) over which the symmetry axis is compared with VP.
NEAR = (10.0, 40.0)
#: Largest lateral distance (mm) of VP from the symmetry axis below it (the shoulders'
#: points of the clinic tuning scenes: 23 mm and more).
MAX_OFFSET = 15.0
#: Largest lateral distance (mm) of VP from DM, the trunk imbalance: the simulated backs and
#: clinic bodies reach 29 mm; a decompensated scoliosis rarely exceeds 40-50 mm. A shoulder's
#: or scapula's convex point that the axis check keeps (the centre line pulled off the spine
#: where hair hides the nape and one side of the upper back is not measured) lay 60 mm off.
MAX_IMBALANCE = 50.0
#: Length (mm) of the straight-down line the axis is searched along.
_DEPTH = 100.0


def axis_offset(grid: LevelGrid, curv: Curvature, point: np.ndarray, half_width: float) -> float:
    """Lateral distance (mm, signed ``x``) of the symmetry axis below ``point`` from it.

    Parameters
    ----------
    grid : LevelGrid
        The surface in the level frame.
    curv : Curvature
        Its curvature maps (the symmetry line's scale).
    point : numpy.ndarray
        ``(3,)`` level point (the VP candidate).
    half_width : float
        The trunk's median half-width (mm): sets the symmetry search's reach.

    Returns
    -------
    float
        Median axis ``x`` minus the point's ``x`` over the profiles :data:`NEAR` below the
        point; NaN when the axis is not measured there.
    """
    point = np.asarray(point, dtype=float)
    bottom = point + np.array([0.0, _DEPTH, 0.0])
    line = find_symmetry_line(grid, curv, point, bottom, half_width)
    if not line.found:
        return float("nan")
    below = line.y - point[1]
    sel = (below >= NEAR[0]) & (below <= NEAR[1]) & np.isfinite(line.asymmetry)
    if not sel.any():
        return float("nan")
    return float(np.median(line.raw_x[sel]) - point[0])


def check_vertebra_prominens(
    grid: LevelGrid,
    curv: Curvature,
    vp: Landmark,
    half_width: float,
    *,
    max_offset: float = MAX_OFFSET,
) -> Landmark:
    """``vp`` unchanged, or refused when it lies beside the symmetry axis below it.

    Parameters
    ----------
    grid : LevelGrid
        The surface in the level frame.
    curv : Curvature
        Its curvature maps.
    vp : Landmark
        The VP found by :func:`~rasterserver_plugins.landmarks.find_vertebra_prominens`.
    half_width : float
        The trunk's median half-width (mm).
    max_offset : float, optional
        Largest distance (mm) from the axis (:data:`MAX_OFFSET`).

    Returns
    -------
    Landmark
    """
    if vp.point is None:  # not found
        return vp
    offset = axis_offset(grid, curv, vp.point, half_width)
    if np.isfinite(offset) and abs(offset) > max_offset:
        return Landmark(
            "VP",
            None,
            0.0,
            f"the convex point at the neck's base lies {abs(offset):.0f} mm beside the back's "
            "symmetry axis below it: a shoulder's, not C7 (the nape hidden by hair or a "
            "shadow, or an arm joined to the shoulder?)",
        )
    return vp


def check_imbalance(
    vp: Landmark, dm: Landmark, *, max_imbalance: float = MAX_IMBALANCE
) -> Landmark:
    """``vp`` unchanged, or refused when it lies farther beside DM than a trunk imbalance does.

    Parameters
    ----------
    vp, dm : Landmark
        VP and the dimples' midpoint, in level coordinates (``x`` across the body).
    max_imbalance : float, optional
        Largest ``|VP.x - DM.x|`` (mm) kept (:data:`MAX_IMBALANCE`).

    Returns
    -------
    Landmark
        ``vp``, or VP refused with the distance in its reason; ``vp`` unchanged when either
        is missing.
    """
    if vp.point is None or dm.point is None:
        return vp
    offset = abs(float(vp.point[0] - dm.point[0]))
    if offset <= max_imbalance:
        return vp
    return Landmark(
        "VP",
        None,
        0.0,
        f"the convex point at the neck's base lies {offset:.0f} mm beside DM, more than a "
        f"trunk imbalance ({max_imbalance:.0f} mm): a shoulder's or scapula's, not C7 (the nape "
        "hidden by hair or a shadow?); a patient this far out of balance needs the "
        "limit raised (analysis parameter vp_max_imbalance)",
    )


def check_confidence(vp: Landmark, *, min_confidence: float = 0.0) -> Landmark:
    """``vp`` unchanged, or refused when its confidence (strength times distinctness,
    :mod:`.landmarks`) is below ``min_confidence``.

    On the clinic bodies 60800-60999 (``benchmarks/clinic_analysis.py``) a weak convex point
    on the upper back, 88 mm from C7, was taken for VP with confidence 0.27; the other 355
    VPs found on those bodies and their backs alone, all within 5.1 mm, had 0.70 or more.
    Analysis version 12 refuses below 0.5 (judged on fresh bodies 61000-61199: one right
    VP of 352 refused, nothing else changed; BENCHMARKS.md "Real bodies" (46)).

    Parameters
    ----------
    vp : Landmark
        VP as found.
    min_confidence : float, optional
        Least confidence kept; 0 keeps every VP.

    Returns
    -------
    Landmark
        ``vp``, or VP refused with its confidence in the reason.
    """
    if vp.point is None or vp.confidence >= min_confidence:
        return vp
    return Landmark(
        "VP",
        None,
        0.0,
        f"the convex point at the neck's base is weak or not distinct (confidence "
        f"{vp.confidence:.2f}, below {min_confidence:.2f}): not taken for C7",
    )
