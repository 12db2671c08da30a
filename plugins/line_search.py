"""Line search: join the peaks of neighbouring columns into raster lines, hierarchically.

The seed's method, vectorised:

1. **Links.** A peak links to the nearest peak of the next column when that peak's nearest
   peak in the previous column is it (mutual nearest neighbours) and the row step is within
   ``max_step``. Each peak has at most one link on each side, so the links form *chains*.
2. **Corners.** The body is smooth, so its raster lines are smooth: a link whose row step
   departs from the steps around it by more than ``corner`` pixels (a sharp corner, the
   second difference of the row along the chain) joins two different lines and is cut.
3. **Hierarchy.** Lines are built from the brightest parts first. At each of a few falling
   area thresholds (the area smoothed along the chain), the runs of chained peaks above the
   threshold are examined: a run without a line becomes a new line if it is long enough; a
   run touching one line extends it (dilation); a run touching two lines is split between
   them at its weakest peak when that is a pronounced intensity minimum (``dip`` times the
   lines' areas around it). A pronounced minimum along a chain (the shoulder blade, the
   arm/trunk boundary) therefore separates two lines seeded on either side of it, as in the
   seed. A shallow minimum only means that noise or shading crossed a threshold, and the two
   fragments are one line.

Chains are laid out once in chain order (a permutation computed without sorting); each level
works on the still unlabelled peaks only, so the levels together cost about one pass over the
peaks. The scans along chains and the levels are compiled loops (:mod:`.chain_scans`,
:mod:`.line_levels`).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field

from rasterserver.records_lines import Lines, Peaks
from rasterserver.stage import Stage, StageContext, StageParams

__all__ = ["HierarchicalLineSearch", "link_peaks", "search_lines"]

DEFAULT_LEVELS: tuple[float, ...] = (2.0, 1.4, 1.0, 0.7, 0.5, 0.35, 0.0)


def link_peaks(
    col: np.ndarray, row: np.ndarray, *, max_step: float = 4.0
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual-nearest-neighbour links between peaks of adjacent columns.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peak columns and rows, sorted by ``(col, row)``.
    max_step : float
        Largest row step of a link (px).

    Returns
    -------
    right, left : numpy.ndarray
        ``(N,)`` int64 index of the linked peak in the next / previous column, -1 for none.
    """
    n = col.size
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    from .line_links import mutual_links  # compiled; the numba import costs ~0.3 s

    span = float(np.ceil(row.max() - min(row.min(), 0.0))) + 2.0 * max_step + 2.0
    return mutual_links(
        np.ascontiguousarray(col, dtype=np.int64),
        np.ascontiguousarray(row, dtype=np.float64),
        span,
        float(max_step),
    )


def _chain_layout(left: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chain order of peaks: ``perm`` (position → peak) and each position's chain head.

    One pass in peak order finds every peak's chain head (:func:`.line_links.chain_heads`);
    a link always advances one column, so the depth along the chain is the column
    difference, and positions follow from the chain lengths: no sort.
    """
    from .chain_scans import chain_order
    from .line_links import chain_heads

    head = chain_heads(np.ascontiguousarray(left, dtype=np.int64))
    return chain_order(head, col)


def _corner_cuts(r: np.ndarray, linked: np.ndarray, corner: float) -> np.ndarray:
    """Links (by position ``k``: between ``k - 1`` and ``k``) that make a sharp corner."""
    from .chain_scans import corner_cuts  # compiled; the numba import costs ~0.3 s

    return corner_cuts(r, linked, float(corner))


def _smooth_along(a: np.ndarray, linked: np.ndarray, half: int) -> np.ndarray:
    """Mean of ``a`` over ``±half`` positions of the same chain (chain-ordered arrays).

    ``linked[k]`` tells whether position ``k`` continues the chain of ``k - 1``; the window
    is clipped to the chain, and its sum taken from a cumulative sum.
    """
    from .chain_scans import smooth_along  # compiled; the numba import costs ~0.3 s

    return smooth_along(a, linked, int(half))


def _turn_cuts(r: np.ndarray, linked: np.ndarray, turn: float, half: int) -> np.ndarray:
    """Links (by position ``k``: between ``k - 1`` and ``k``) where the chain turns by more
    than ``turn`` px per column between the ``half`` links before and after."""
    from .chain_scans import turn_cuts  # compiled; the numba import costs ~0.3 s

    return turn_cuts(r, linked, float(turn), int(half))


def _step_cuts(a: np.ndarray, linked: np.ndarray, half: int, ratio: float) -> np.ndarray:
    """Links (by position ``k``: between ``k - 1`` and ``k``) across which the peak area
    steps by more than ``ratio``: the mean of the ``half`` peaks before against the ``half``
    after, same chain, only the strongest link of a step.

    A raster line keeps its kind along its length and the skin's shading changes slowly, so
    a sharp step of the area marks a change of surface (skin to clothing at a waistband, a
    hand on the hip) where the depth may step by a whole line spacing and the chain may run
    from one raster line onto the next.
    """
    n = a.size
    if n < 2 * half or half < 1:
        return np.zeros(n, dtype=bool)
    # the two sides' means and the strongest links in compiled loops (chain_scans; the
    # numba import costs ~0.3 s); the logarithms stay numpy's
    from .chain_scans import step_peaks, step_ratios

    ratio_at, full = step_ratios(a, linked, int(half))
    with np.errstate(divide="ignore", invalid="ignore"):
        jump = np.abs(np.log(ratio_at))
    # both sides need ``half`` peaks: a short run at a chain's end says nothing
    return step_peaks(jump, full, float(np.log(ratio)))


def _side_max(
    a: np.ndarray, head: np.ndarray, at: np.ndarray, step: int, window: int
) -> np.ndarray:
    """Largest ``a`` within ``window`` positions from ``at`` in direction ``step``, same chain.

    The levels' loop (:func:`.line_levels.level_labels`) searches one run at a time; this
    array form is the tests' reference for the replaced passes.
    """
    from .chain_scans import side_maxima  # compiled; the numba import costs ~0.3 s

    return side_maxima(a, head, np.ascontiguousarray(at, dtype=np.int64), int(step), int(window))


def _roots(parent: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Union-find roots of ``ids`` (-1 stays -1): each followed up the parent array.

    As :func:`_side_max`, the array form the tests' reference of the levels calls.
    """
    ids = np.asarray(ids, dtype=np.int64)
    if parent.size == 0:
        return ids
    from .chain_scans import union_roots  # compiled; the numba import costs ~0.3 s

    return union_roots(parent, np.ascontiguousarray(ids))


def search_lines(
    col: np.ndarray,
    row: np.ndarray,
    area: np.ndarray,
    *,
    max_step: float = 4.0,
    corner: float = 1.5,
    levels: tuple[float, ...] = DEFAULT_LEVELS,
    dip: float = 0.6,
    dip_window: int = 20,
    smooth: int = 2,
    min_seed: int = 8,
    min_length: int = 3,
    step_ratio: float | None = 1.6,
    step_half: int = 3,
    turn: float | None = None,
    turn_half: int = 3,
    vertex: bool = False,
) -> np.ndarray:
    """Line id of every peak (-1: in no line), by hierarchical line search.

    Parameters
    ----------
    col, row, area : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    max_step : float
        Largest row step between peaks of adjacent columns (px).
    corner : float
        Largest departure of a link's row step from the steps around it (px); sharper
        corners are cut.
    levels : tuple of float
        Area thresholds, as multiples of the median peak area, highest first. A last level
        of 0 lets every remaining chained peak join a line.
    dip : float
        A run joining two lines is split at its weakest peak when that peak's (smoothed)
        area is below ``dip`` times the smaller of the two lines' largest areas within
        ``dip_window`` peaks of the run: a pronounced intensity minimum. Shallower minima
        come from noise or shading around a threshold, and the two lines are one.
    dip_window : int
        Peaks on each side of a run searched for the lines' areas.
    smooth : int
        Half-width (peaks) of the running mean of the area along the chains; per-peak noise
        must not make or hide a minimum.
    min_seed : int
        Least number of peaks of a new line started at any level but the last.
    min_length : int
        Least number of peaks of a line; shorter ones are dropped (-1).
    step_ratio : float or None
        A link across which the mean area of the ``step_half`` peaks on either side changes
        by more than this factor is cut (a change of surface, see :func:`_step_cuts`);
        None keeps such links.
    step_half : int
        Peaks on each side of a link compared for an area step.
    turn : float or None
        A link where the mean row step of the ``turn_half`` links before and the
        ``turn_half`` links after it differ by more than this (px per column) is cut: a
        line on one smooth surface does not turn so within a few columns, and where it
        does, the chain has run from one surface's line onto another's at a contour (an
        arm's or a cloth's edge), the corner rounded by the peaks at the contour so that
        no single link departs by ``corner``. None keeps such links.
    turn_half : int
        Links on each side of a link whose mean steps are compared for a turn.
    vertex : bool
        Also cut, beside every corner cut, the neighbouring link that departs more from the
        steps beside it, so that the peak at the vertex joins neither line: where two
        surfaces' lines meet in a corner, it may belong to either.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` int32 line ids, ``0 .. L - 1`` numbered by the line's first peak (lowest
        column, then row), -1 for peaks in no line.
    """
    n = col.size
    if n == 0:
        return np.zeros(0, dtype=np.int32)
    _, left = link_peaks(col, row, max_step=max_step)
    perm, head = _chain_layout(left, col)
    r = row[perm]
    linked = np.zeros(n, dtype=bool)
    linked[1:] = head[1:] == head[:-1]
    cut = _corner_cuts(r, linked, corner)
    if vertex:
        from .chain_scans import vertex_cuts  # compiled; the numba import costs ~0.3 s

        cut = vertex_cuts(r, linked, cut)
    if turn is not None:
        # a turn's vertex is not cut out: the lines bending towards a silhouette turn too,
        # and one more peak of each is the back's
        cut |= _turn_cuts(r, linked, turn, turn_half)
    linked &= ~cut
    a = area[perm].astype(np.float64)
    if step_ratio is not None:
        linked &= ~_step_cuts(a, linked, step_half, step_ratio)
    if smooth > 0:
        a = _smooth_along(a, linked, smooth)
    from .line_links import ranked_labels

    # Chains cut at corners and area steps are separate chains from here on.
    label = _line_labels(
        a,
        linked,
        perm,
        levels,
        dip=dip,
        dip_window=dip_window,
        min_seed=min_seed,
        min_length=min_length,
    )
    return ranked_labels(label, int(min_length))


def _line_labels(
    a: np.ndarray,
    linked: np.ndarray,
    perm: np.ndarray,
    levels: tuple[float, ...],
    *,
    dip: float,
    dip_window: int,
    min_seed: int,
    min_length: int,
) -> np.ndarray:
    """Line label of every peak (peak order, not yet ranked or filtered) from the levels.

    The levels are one compiled loop (:func:`.line_levels.level_labels`; the numba import
    costs ~0.3 s); the thresholds' scale, the median area, stays numpy's: numba's median
    differs in the last bits.
    """
    from .line_levels import level_labels

    scale = float(np.median(a))
    thresholds = np.array([factor * scale for factor in levels], dtype=np.float64)
    return level_labels(
        a, linked, perm, thresholds, float(dip), int(dip_window), int(min_seed), int(min_length)
    )


class HierarchicalLineSearch(Stage[Peaks, Lines]):
    """Peaks joined into raster lines, brightest parts first, cut at corners and dips.

    Mutual-nearest-neighbour links between adjacent columns form chains; sharp corners cut
    them; lines are seeded at falling area thresholds and grow by dilation, and a run that
    would join two lines is split at its intensity minimum when that is pronounced.

    Version 2: chains are also cut where the peak area steps sharply (a change of surface,
    skin to clothing, where the depth may step by a whole line spacing).

    Version 3: chains are also cut where they turn (the mean row step of the three links
    before and after a link differ by more than 1.3 px per column: one surface's line
    running into another's at a contour, the corner rounded), and the peak at a corner cut
    joins neither line (it lies between both surfaces' courses and may belong to either).
    """

    name: ClassVar[str] = "lines.hierarchical"
    stage: ClassVar[str] = "lines"
    version: ClassVar[str] = "3"
    input_type = Peaks
    output_type = Lines

    class Params(StageParams):
        """Parameters of :class:`HierarchicalLineSearch` (pixels, or multiples of areas)."""

        max_step: float = Field(
            4.0, gt=0, description="Largest row step between adjacent columns (px)."
        )
        corner: float = Field(
            1.5, gt=0, description="Largest change of the row step at a link (px)."
        )
        levels: tuple[float, ...] = Field(
            DEFAULT_LEVELS,
            min_length=1,
            description="Area thresholds as multiples of the median area, highest first.",
        )
        dip: float = Field(
            0.6, gt=0, le=1, description="Area ratio of a pronounced minimum that splits lines."
        )
        dip_window: int = Field(20, ge=1, description="Peaks searched for the lines' areas.")
        smooth: int = Field(2, ge=0, description="Half-width of the area's running mean.")
        min_seed: int = Field(8, ge=1, description="Least peaks of a line started early.")
        min_length: int = Field(3, ge=1, description="Least peaks of a line.")
        step_ratio: float | None = Field(
            2.0,
            gt=1,
            description="Area step along a chain that cuts it (a change of surface); None: off.",
        )
        step_half: int = Field(3, ge=1, description="Peaks each side compared for a step.")
        turn: float | None = Field(
            1.3,
            gt=0,
            description="Change of the mean row step between the links either side of a "
            "link that cuts it (px per column; a line running onto another surface's at "
            "a contour); None: off.",
        )
        turn_half: int = Field(3, ge=1, description="Links each side compared for a turn.")
        vertex: bool = Field(
            True,
            description="The peak at a cut corner joins neither line (where two surfaces' "
            "lines meet it may belong to either).",
        )

    def run(self, data: Peaks, params: Params, context: StageContext) -> Lines:
        """Search the lines of ``data``; no peaks give no lines."""
        line_id = search_lines(
            data.col,
            data.row,
            data.area,
            max_step=params.max_step,
            corner=params.corner,
            levels=tuple(sorted(params.levels, reverse=True)),
            dip=params.dip,
            dip_window=params.dip_window,
            smooth=params.smooth,
            min_seed=params.min_seed,
            min_length=params.min_length,
            step_ratio=params.step_ratio,
            step_half=params.step_half,
            turn=params.turn,
            turn_half=params.turn_half,
            vertex=params.vertex,
        )
        return Lines.extend(data, line_id=line_id)
