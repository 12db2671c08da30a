"""Code evidence of a component of ordered lines: where on the raster's code its lines lie.

Reading the kinds robustly: absolute intensity varies along the back (distance, inclination,
skin), but two neighbouring lines in one column are lit and seen alike, so the ratio of their
peak areas is the ratio of their line widths: 1.5 for a heavy line over a light one (60:40),
1 for equal kinds. For each pair of consecutive levels ``k, k + 1`` of a component, a robust
mean over the columns where they are direct neighbours of ``log(area_k / area_k+1)`` is
``+λ``, ``0`` or ``-λ`` (``λ = log 1.5``), weighted by how decisively it is read.

Every placement of these differences on the code is scored by the number of differences it
explains badly (a soft count, so one misread line costs two differences and no more); the
best must beat the second best by a clear margin. :func:`locally_contradicted` reads the
same evidence on runs of a numbered component's levels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rasterserver.errors import InputError
from rasterserver.raster import Raster

__all__ = [
    "EXPLAINS_TOO_LITTLE",
    "CodeFit",
    "ComponentNumbering",
    "area_ratio_of",
    "code_fit",
    "code_objection",
    "contradicted_lines",
    "level_differences",
    "level_pairs",
    "level_statistics",
    "locally_contradicted",
    "observed_kinds",
    "reliability",
    "robust_centres",
]

# the start of the reason of a component whose best placement leaves too much unexplained
# (the numbering may still place it when that placement is unique by far)
EXPLAINS_TOO_LITTLE = "best code placement explains too little"


def area_ratio_of(raster: Raster, area_ratio: float | None = None) -> float:
    """The peak-area ratio of a heavy to a light line the numbering expects.

    Parameters
    ----------
    raster : Raster
        The diapositive's code.
    area_ratio : float, optional
        The ratio set by the user; by default the ratio of the raster's median heavy to
        median light line width (1.5 for a raster of one kind only).

    Returns
    -------
    float
        The ratio, above 1.

    Raises
    ------
    InputError
        When the ratio is not above 1 (the kinds could not be told apart).
    """
    if area_ratio is None:
        code = raster.code
        heavy = raster.widths[code == 1]
        light = raster.widths[code == 0]
        area_ratio = (
            float(np.median(heavy) / np.median(light)) if heavy.size and light.size else 1.5
        )
    if area_ratio <= 1.0:
        raise InputError(f"the heavy/light area ratio must exceed 1, got {area_ratio:g}")
    return float(area_ratio)


def level_differences(
    col: np.ndarray,
    area: np.ndarray,
    line_id: np.ndarray,
    line_order: np.ndarray,
    line_component: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robust mean log-area ratio of every pair of consecutive levels, per component.

    Parameters
    ----------
    col, area, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_order, line_component : numpy.ndarray
        Per-line relative order and component (-1: unordered).

    Returns
    -------
    comp, level, ratio, count : numpy.ndarray
        One entry per (component, level ``k``) with measurements: the robust mean over
        columns of ``log(area at k / area at k + 1)`` where a line of level ``k`` lies
        directly above one of level ``k + 1``, and the number of such columns.
    """
    comp, level, ratio, count, _ = level_statistics(col, area, line_id, line_order, line_component)
    return comp, level, ratio, count


def level_statistics(
    col: np.ndarray,
    area: np.ndarray,
    line_id: np.ndarray,
    line_order: np.ndarray,
    line_component: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`level_differences` plus the spread of the column ratios about their centre.

    Returns
    -------
    comp, level, ratio, count, spread : numpy.ndarray
        As :func:`level_differences`; ``spread`` is the mean absolute deviation of the
        (clipped) column log ratios from the robust centre: large where the albedo is uneven
        (hair, naevi, a clothing edge), so that the ratio says little about the line widths.
    """
    empty_i = np.zeros(0, dtype=np.int64)
    empty = (empty_i, empty_i, np.zeros(0), empty_i, np.zeros(0))
    if col.size < 2 or line_order.size == 0:
        return empty
    from .column_pairs import peak_levels  # compiled; the numba import costs ~0.3 s

    comp_of, lev_of = peak_levels(line_id, line_order, line_component)
    k, lr = level_pairs(col, area, comp_of, lev_of)
    if k.size == 0:
        return empty
    comp, level = comp_of[k], lev_of[k]
    span = int(lev_of.max()) + 2
    groups, centre, counts, spread = robust_centres(comp * span + level, lr)
    return groups // span, groups % span, centre, counts, spread


def level_pairs(
    col: np.ndarray, area: np.ndarray, comp_of: np.ndarray, lev_of: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Column neighbours on consecutive levels of one component, and their log area ratio.

    Parameters
    ----------
    col, area : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    comp_of, lev_of : numpy.ndarray
        Per-peak component and level (-1: none).

    Returns
    -------
    k, lr : numpy.ndarray
        Index of the upper peak of every such pair (the lower is ``k + 1``) and
        ``log(area[k] / area[k + 1])``; pairs whose ratio is not finite are left out.
    """
    # the pairs and their area ratios in one compiled loop (column_pairs; the numba import
    # costs ~0.3 s, hence here); the logarithm stays numpy's
    from .column_pairs import level_pair_ratios

    k, ratio = level_pair_ratios(col, area, comp_of, lev_of)
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(ratio)
    good = np.isfinite(lr)
    return k[good], lr[good]


_CENTRE_WINDOWS = np.array([0.3, 0.15])


def robust_centres(
    key: np.ndarray, lr: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Robust centre of the log ratios ``lr`` sharing a key, their count and spread.

    Parameters
    ----------
    key : numpy.ndarray
        Non-negative int64 group of every ratio (small: counted by ``bincount``).
    lr : numpy.ndarray
        Column log area ratios.

    Returns
    -------
    groups, centre, count, spread : numpy.ndarray
        One entry per key present, ascending.
    """
    # A robust centre without sorting: the mean of the clipped ratios, then twice the mean
    # of those near the previous centre (silhouette columns and skin spots are outliers).
    # One compiled loop per pass (ratio_groups); the numba import costs ~0.3 s, hence here.
    from .ratio_groups import grouped_centres

    return grouped_centres(
        np.ascontiguousarray(key, dtype=np.int64),
        np.ascontiguousarray(lr, dtype=np.float64),
        _CENTRE_WINDOWS,
    )


@dataclass(frozen=True)
class ComponentNumbering:
    """How one component was numbered.

    Attributes
    ----------
    component : int
        Component index.
    n_levels : int
        Number of levels (relative orders) in the component.
    offset : int
        Index into the raster's lines of level 0; -1 when refused.
    cost : float
        Soft count of badly explained differences of the best placement.
    margin : float
        Cost of the second-best placement minus the best's.
    kinds : numpy.ndarray
        ``(n_levels,)`` int8 observed kind of each level: 0 light, 1 heavy, -1 unknown.
    reason : str
        Why it was refused; empty when numbered.
    how : str
        How it was numbered: ``"code"`` (its own code), ``"linked"`` (inherited from the
        numbered components it touches), ``"group"`` (inherited with the small components
        it is tied to, :mod:`.component_groups`); empty when refused.
    """

    component: int
    n_levels: int
    offset: int
    cost: float
    margin: float
    kinds: np.ndarray
    reason: str
    how: str = ""


def observed_kinds(d: np.ndarray, weight: np.ndarray, lam: float, tolerance: float) -> np.ndarray:
    """Most likely kind of every level from the differences alone (no code), by Viterbi.

    ``d[k] ≈ (kind[k] - kind[k + 1]) * lam``; the same robust cost as the placement. Levels
    without a measured difference on either side, or whose two kinds explain the data
    equally well, are unknown (-1).
    """
    if d.size == 0:
        return np.full(d.size + 1, -1, dtype=np.int8)
    # forward and backward passes give each level's best total cost per kind: one compiled
    # loop (code_placements; the numba import costs ~0.3 s, hence here)
    from .code_placements import level_kinds

    return level_kinds(
        np.ascontiguousarray(d, dtype=np.float64),
        np.ascontiguousarray(weight, dtype=np.float64),
        float(lam),
        float(tolerance),
    )


@dataclass(frozen=True)
class CodeFit:
    """The code evidence of one component: cost of every placement."""

    cost: np.ndarray  # (offsets,) soft count of badly explained differences; empty if none
    terms: float  # total weight of the measured differences
    best: int
    margin: float
    reason: str  # why the code alone does not decide; empty when it does


def code_fit(
    n_levels: int,
    d: np.ndarray,
    weight: np.ndarray,
    code: np.ndarray,
    *,
    lam: float,
    tolerance: float,
    min_lines: int,
    min_margin: float,
    max_cost_rate: float,
) -> CodeFit:
    n_off = code.size - n_levels + 1
    if n_off < 1:
        return CodeFit(np.zeros(0), 0.0, -1, 0.0, f"{n_levels} lines, more than the raster's")
    # every placement's cost in one compiled loop (code_placements; the numba import costs
    # ~0.3 s, hence here), summed in numpy's order; best two as a stable argsort's first two
    from .code_placements import best_two, placement_costs

    if n_levels >= 2:
        cost, terms, n_measured = placement_costs(
            np.ascontiguousarray(d, dtype=np.float64),
            np.ascontiguousarray(weight, dtype=np.float64),
            code.astype(np.float64),
            float(lam),
            float(tolerance),
        )
    else:
        measured = (~np.isnan(d)) & (weight > 0)
        terms = float(weight[measured].sum())
        n_measured = int(measured.sum())
        cost = np.zeros(n_off)
    best, second = best_two(cost)
    best_cost = float(cost[best])
    margin = float(cost[second] - best_cost) if n_off > 1 else float("inf")
    if n_levels < min_lines:
        reason = f"{n_levels} lines, fewer than {min_lines}"
    elif n_measured < min_lines - 1 or terms < 0.5 * (min_lines - 1):
        reason = (
            f"only {n_measured} reliable neighbour intensity ratios "
            f"(weight {terms:.1f}; uneven albedo or too few columns)"
        )
    elif best_cost > max_cost_rate * terms:
        reason = f"{EXPLAINS_TOO_LITTLE} ({best_cost:.1f} of {terms:.0f} bad)"
    elif margin < min_margin - 1e-9:
        reason = f"ambiguous code placement (margin {margin:.2f} < {min_margin:g})"
    else:
        reason = ""
    return CodeFit(cost, terms, best, margin, reason)


def code_objection(fit: CodeFit, off: int, n_off: int, max_cost_rate: float) -> str:
    """Why a component's own code speaks against the placement ``off`` its neighbours imply.

    Parameters
    ----------
    fit : CodeFit
        The component's code fit.
    off : int
        The placement (index of its level 0 on the code).
    n_off : int
        Number of placements on the code.
    max_cost_rate : float
        Largest cost per measured difference of an acceptable placement.

    Returns
    -------
    str
        Empty when the code does not object: the placement lies on the code and costs at
        most one misread difference more than the best, and within the rate.
    """
    if not 0 <= off < n_off:
        return f"its neighbours imply a placement off the code ({off})"
    if fit.cost.size and fit.terms > 0:
        excess = float(fit.cost[off] - fit.cost.min())
        if excess > 1.0 or fit.cost[off] > max_cost_rate * fit.terms + 1.0:
            return (
                f"its code contradicts the number its neighbours imply (excess cost {excess:.1f})"
            )
    return ""


def reliability(
    count: np.ndarray, spread: np.ndarray, lam: float, correlation: float
) -> np.ndarray:
    """How decisively each level difference is read, in [0, 1].

    The standard error of the robust centre (spread over the square root of the number of
    independent columns; neighbouring columns see the same albedo texture, hence
    ``correlation``) against half the heavy/light step ``lam / 2``: z <= 1 is worthless,
    z >= 3 full weight.
    """
    n_eff = np.maximum(count / correlation, 1.0)
    se = np.maximum(1.25 * spread / np.sqrt(n_eff), 0.01)
    z = 0.5 * lam / se
    return np.clip((z - 1.0) / 2.0, 0.0, 1.0)


def locally_contradicted(
    d: np.ndarray,
    w: np.ndarray,
    code: np.ndarray,
    offset: int,
    span: int,
    lam: float,
    tolerance: float,
    min_margin: float,
    max_cost_rate: float,
    poor_factor: float = 2.0,
) -> np.ndarray:
    """Levels of a numbered component where a run of ``span`` levels contradicts the
    component's placement: it reads, on its own, uniquely and cleanly as another placement,
    or (with ``poor_factor`` > 0) the component's placement explains it far worse (over
    ``poor_factor`` times ``max_cost_rate``) than another. Line sequence analysis then put
    those lines one or more levels off (a clothing edge, a fold), and the component's single
    offset would number them wrongly."""
    n_levels = d.size + 1
    if n_levels < span + 2:
        return np.zeros(0, dtype=np.int64)
    # one compiled loop per run and placement (level_runs); the numba import costs ~0.3 s
    from .level_runs import contradicted_levels

    bad = contradicted_levels(
        np.ascontiguousarray(d, dtype=np.float64),
        np.ascontiguousarray(w, dtype=np.float64),
        code.astype(np.float64),
        int(offset),
        int(span),
        float(lam),
        float(tolerance),
        float(min_margin),
        float(max_cost_rate),
        float(poor_factor),
    )
    return np.flatnonzero(bad)


def contradicted_lines(
    placed: dict[int, int],
    diffs: dict[int, tuple[np.ndarray, np.ndarray]],
    comps: np.ndarray,
    levels: np.ndarray,
    valid: np.ndarray,
    code: np.ndarray,
    span: int,
    lam: float,
    tolerance: float,
    min_margin: float,
    max_cost_rate: float,
    poor_factor: float,
) -> np.ndarray:
    """Lines of numbered components in a run of levels that contradicts their placement.

    Parameters
    ----------
    placed : dict
        Component -> its placement (offset on the code), for the components judged.
    diffs : dict
        Component -> its level differences and their weights.
    comps, levels : numpy.ndarray
        ``(L,)`` component and level of every line.
    valid : numpy.ndarray
        ``(L,)`` bool, lines with a component and a level.
    code, span, lam, tolerance, min_margin, max_cost_rate, poor_factor
        As :func:`locally_contradicted`.

    Returns
    -------
    numpy.ndarray
        ``(L,)`` bool, the lines to leave unnumbered.
    """
    bad = np.zeros(valid.shape[0], dtype=bool)
    for c, off in placed.items():
        d, w = diffs[c]
        levels_bad = locally_contradicted(
            d, w, code, off, span, lam, tolerance, min_margin, max_cost_rate, poor_factor
        )
        if levels_bad.size:
            bad |= valid & (comps == c) & np.isin(levels, levels_bad)
    return bad
