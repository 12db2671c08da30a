"""Line sequence analysis: arrange whole lines in their natural top-to-bottom order.

The seed's method, one hierarchical level above line search:

1. **Neighbourhoods.** In every column, two consecutive peaks that belong to two different
   lines, with no other peak between them, make the upper line a direct neighbour of the
   lower one in that column. A gap much wider than the gaps above and below it in the same
   column, or than the typical gap in its part of the image (``gap_ratio``), means a line
   is missing between them there, and is not counted.
   The number of such columns is the length of the pair's mutual neighbourhood.
2. **Order.** Pairs are taken longest neighbourhood first (ties: longer lines first). A pair
   either joins two groups of ordered lines (the lower line one below the upper) or, inside
   a group, must agree with the order already built; a pair that contradicts it is
   rejected. Every line is thus classified once, by its most reliable relation, and a short
   or accidental neighbourhood (an arm's line meeting the trunk's at the silhouette) cannot
   overturn a long one. A neighbourhood shorter than ``min_link`` columns does not link two
   groups by itself: where lines crowd at a fold a missing line is easily taken for none,
   so short neighbourhoods link groups only when several agree on the shift and add up to
   ``min_link`` columns. A line whose neighbourhoods contradict its place about as much as
   they support it (a line vanishing behind a fold leaves its neighbours above and below
   disagreeing) is *contested*: it is left out and the order rebuilt without it. Lines left
   alone are not numbered, which is better than wrongly.
   An option (``end_overlaps_link`` off; tried as version 2, not adopted): two lines that
   overlap only by their ends, over fewer than ``min_link`` columns (the upper one ends
   where the lower one begins, or the reverse), are not neighbours at all: that staircase
   is the trace of a contour crossing the lines (the corner of a waistband, an arm's
   edge), across which the surfaces' depth step, and with it the number of lines between
   the two, is unknown (:func:`end_overlaps`).
3. Groups that no pair links stay separate *components*, each with its own relative order
   from 0 (top) down; line numbering decides each component's offset on its own.

The neighbourhoods are found with a few vectorised passes over the peaks; the ordering loop
runs over line pairs (a few hundred), not peaks.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import Field

from rasterserver.records_lines import Lines, OrderedLines
from rasterserver.stage import Stage, StageContext, StageParams

__all__ = [
    "HierarchicalLineOrder",
    "LineOrder",
    "end_overlaps",
    "line_neighbours",
    "order_lines",
]


def line_neighbours(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    n_lines: int,
    *,
    gap_ratio: float = 1.6,
    cell: int = 24,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of lines that are direct neighbours in some columns, and in how many.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)`` and their lines (-1: none).
    n_lines : int
        Number of lines.
    gap_ratio : float
        A neighbourhood in a column counts only when its row gap is at most ``gap_ratio``
        times the mean of the gaps directly above and below it in that column, and
        ``gap_ratio`` times the typical gap in its ``cell`` x ``cell`` pixel cell.
    cell : int
        Cell size (px) of the typical gap.

    Returns
    -------
    upper, lower, count : numpy.ndarray
        int64 arrays, one entry per pair: ``upper`` is directly above ``lower`` in
        ``count`` columns more than it is below it, or above it with unlined peaks between
        (only pairs with a positive count).
    """
    n = col.size
    empty = np.zeros(0, dtype=np.int64)
    if n < 2 or n_lines < 2:
        return empty, empty, empty
    # Every column's neighbourhoods in compiled loops (line_contacts; the numba import
    # costs ~0.3 s, hence here). A pair counts when its gap is at most gap_ratio times the
    # mean of the gaps directly above and below it in its column, and gap_ratio times the
    # typical spacing around it: the mean gap in its cell of the image, after dropping gaps
    # far above a first mean (the missing lines themselves). An isolated pair (no gaps
    # above or below it in its column) is judged by the latter alone.
    from .line_contacts import neighbour_keys

    pair_keys, skip_keys = neighbour_keys(col, row, line_id, n_lines, float(gap_ratio), cell)
    if pair_keys.size == 0:
        return empty, empty, empty
    keys, counts = _count_pairs(pair_keys, n_lines)
    if keys.size == 0:
        return empty, empty, empty
    upper, lower = keys // n_lines, keys % n_lines
    # The same two lines seen the other way round somewhere: keep the dominant arrangement.
    net = counts - _lookup(keys, counts, lower * n_lines + upper)
    # Columns where the two lines follow each other with unlined peaks between them: a line
    # is there that the pair skips (a line too broken to be searched, where lines crowd at
    # a fold), so where it is not detected the two are not neighbours either. Such columns
    # count against the pair.
    if skip_keys.size:
        s_keys, s_counts = _count_pairs(skip_keys, n_lines)
        net = net - _lookup(s_keys, s_counts, keys)
    keep = net > 0
    return upper[keep], lower[keep], net[keep]


def end_overlaps(
    col: np.ndarray,
    line_id: np.ndarray,
    upper: np.ndarray,
    lower: np.ndarray,
    n_lines: int,
    min_span: int,
) -> np.ndarray:
    """Per pair of lines, whether they overlap only by their ends over fewer than
    ``min_span`` columns.

    Where a contour crosses the raster's lines (the corner of a waistband, an arm's edge),
    the lines of one surface end along it and those of the other begin: in the few columns
    where both are seen, one surface's line lies directly above the other's, at whatever
    row the depth step between the surfaces puts it. A cloth standing off the skin can put
    its line ``n + 1`` one spacing below the skin's line ``n - 1`` there, and several such
    pairs along the contour agree on that shift. On one surface two neighbouring lines run
    side by side over many columns, or one lies within the other's span (a piece of a line
    broken by a shadow).

    Parameters
    ----------
    col, line_id : numpy.ndarray
        Peaks' columns and lines (-1: none).
    upper, lower : numpy.ndarray
        int64 line indices of the pairs.
    n_lines : int
        Number of lines.
    min_span : int
        Least span (columns, from the later first column to the earlier last one) of an
        overlap by the ends that is not such a staircase.

    Returns
    -------
    numpy.ndarray
        Bool per pair: one line begins left of the other and also ends left of its end,
        and the two share fewer than ``min_span`` columns of their spans.
    """
    inside = line_id >= 0
    lid = line_id[inside].astype(np.int64)
    c = col[inside].astype(np.int64)
    first = np.full(n_lines, np.iinfo(np.int64).max, dtype=np.int64)
    last = np.full(n_lines, -1, dtype=np.int64)
    np.minimum.at(first, lid, c)
    np.maximum.at(last, lid, c)
    u0, u1, v0, v1 = first[upper], last[upper], first[lower], last[lower]
    staggered = ((u0 < v0) & (u1 < v1)) | ((v0 < u0) & (v1 < u1))
    span = np.minimum(u1, v1) - np.maximum(u0, v0) + 1
    return staggered & (span >= 1) & (span < min_span)


def _count_pairs(pair_key: np.ndarray, n_lines: int) -> tuple[np.ndarray, np.ndarray]:
    """Distinct pair keys (sorted) and how often each occurs."""
    if pair_key.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if n_lines * n_lines <= 1 << 22:
        # counting beats sorting while the pair table stays small (a few MB)
        table = np.bincount(pair_key, minlength=n_lines * n_lines)
        keys = np.flatnonzero(table)
        return keys, table[keys]
    return np.unique(pair_key, return_counts=True)


def _lookup(keys: np.ndarray, counts: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Count of each ``query`` key in the sorted ``keys`` (0 when absent)."""
    if keys.size == 0:
        return np.zeros(query.size, dtype=np.int64)
    pos = np.minimum(np.searchsorted(keys, query), keys.size - 1)
    return np.where(keys[pos] == query, counts[pos], 0)


@dataclass(frozen=True)
class LineOrder:
    """Result of :func:`order_lines`.

    Attributes
    ----------
    order : numpy.ndarray
        ``(L,)`` int32 relative order of each line within its component (0 = top), -1 when
        the line is unordered.
    component : numpy.ndarray
        ``(L,)`` int32 component of each line, numbered by size (peaks) descending; -1 when
        unordered.
    rejected : int
        Neighbourhood columns of the pairs that contradict the final order.
    contested : int
        Lines left out because their neighbourhoods contradict each other.
    """

    order: np.ndarray
    component: np.ndarray
    rejected: int
    contested: int = 0


def _build_order(
    n_lines: int,
    upper: np.ndarray,
    lower: np.ndarray,
    count: np.ndarray,
    sizes: np.ndarray,
    min_link: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Group and level of every line from the neighbourhoods (both phases)."""
    # Groups with explicit member lists: merging relabels the smaller group, so the whole
    # loop costs O(pairs + lines log lines).
    group = list(range(n_lines))
    level = [0] * n_lines
    members: dict[int, list[int]] = {i: [i] for i in range(n_lines)}

    def merge(ga: int, gb: int, shift: int) -> None:
        """Join group ``gb`` to ``ga``, its levels moved by ``shift``."""
        if len(members[gb]) > len(members[ga]):
            ga, gb, shift = gb, ga, -shift
        for x in members[gb]:
            group[x] = ga
            level[x] += shift
        members[ga].extend(members.pop(gb))

    # Phase 1: neighbourhoods of at least min_link columns, longest first (ties: the longer
    # of the shorter line); each either links two groups or is checked against the order.
    strong = count >= min_link
    su, sv, sw = upper[strong], lower[strong], count[strong]
    shorter = np.minimum(sizes[su], sizes[sv])
    for e in np.lexsort((-shorter, -sw)).tolist():
        u, v = int(su[e]), int(sv[e])
        if group[u] != group[v]:
            merge(group[u], group[v], level[u] + 1 - level[v])
    # Phase 2: a short neighbourhood alone may be a missing line taken for none (where the
    # lines crowd at a fold); groups are linked by short neighbourhoods only when those
    # between them agree on the shift and add up to min_link columns.
    wu, wv, ww = upper[~strong], lower[~strong], count[~strong]
    while wu.size:
        g = np.asarray(group, dtype=np.int64)
        lv = np.asarray(level, dtype=np.int64)
        gu, gv = g[wu], g[wv]
        cross = gu != gv
        if not np.any(cross):
            break
        shift = (lv[wu] + 1 - lv[wv])[cross]
        gu, gv, w = gu[cross], gv[cross], ww[cross]
        flip = gu > gv
        ga, gb = np.where(flip, gv, gu), np.where(flip, gu, gv)
        shift = np.where(flip, -shift, shift)
        # one integer key per (group pair, shift): 1-D unique is far cheaper than rows
        # (levels stay within ±n_lines, so shifts within ±2 n_lines)
        span = 4 * n_lines + 3
        pair = ga * n_lines + gb
        keys, inv = np.unique(pair * span + (shift + 2 * n_lines + 1), return_inverse=True)
        votes = np.bincount(inv, weights=w)
        key_pair = keys // span
        _, pinv = np.unique(key_pair, return_inverse=True)
        pair_total = np.bincount(pinv, weights=votes)[pinv]
        ok = (votes >= min_link) & (votes >= 2.0 * (pair_total - votes))
        if not np.any(ok):
            break
        best = int(np.flatnonzero(ok)[np.argmax(votes[ok])])
        a_best, b_best = divmod(int(key_pair[best]), n_lines)
        merge(a_best, b_best, int(keys[best] % span) - 2 * n_lines - 1)
    return np.asarray(group, dtype=np.int64), np.asarray(level, dtype=np.int64)


def order_lines(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    *,
    gap_ratio: float = 1.6,
    min_overlap: int = 3,
    min_link: int = 6,
    max_conflict: float = 0.5,
    end_overlaps_link: bool = True,
) -> LineOrder:
    """Relative order of the lines, component by component.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)`` and their lines (-1: none).
    gap_ratio : float
        See :func:`line_neighbours`.
    min_overlap : int
        Least number of columns of a neighbourhood considered at all.
    min_link : int
        Least number of columns of a neighbourhood that links two groups of lines by
        itself; shorter ones link groups only together, when they agree.
    max_conflict : float
        A line whose neighbourhood columns contradicting its place reach this share of those
        supporting it is left out (a component of its own, not numbered).
    end_overlaps_link : bool
        Count the neighbourhoods of lines that overlap only by their ends over fewer than
        ``min_link`` columns (:func:`end_overlaps`), as version 1 does; off, they are not
        neighbours (the option tried as version 2).

    Returns
    -------
    LineOrder
        Lines without any neighbourhood are components of their own (order 0).
    """
    n_lines = int(line_id.max()) + 1 if line_id.size else 0
    if n_lines == 0:
        z = np.zeros(0, dtype=np.int32)
        return LineOrder(order=z, component=z.copy(), rejected=0)
    upper, lower, count = line_neighbours(col, row, line_id, n_lines, gap_ratio=gap_ratio)
    sizes = np.bincount(line_id[line_id >= 0], minlength=n_lines)
    usable = count >= min_overlap
    if not end_overlaps_link:
        usable &= ~end_overlaps(col, line_id, upper, lower, n_lines, min_link)
    upper, lower, count = upper[usable], lower[usable], count[usable]
    # A line whose neighbourhoods contradict its place almost as much as they support it
    # (where a line vanishes behind a fold, its neighbours above and below disagree) is
    # contested: it is left out, and the order rebuilt without it.
    excluded = np.zeros(n_lines, dtype=bool)
    for attempt in range(5):
        keep = ~excluded[upper] & ~excluded[lower]
        group_arr, level_arr = _build_order(
            n_lines, upper[keep], lower[keep], count[keep], sizes, min_link
        )
        inside = keep & (group_arr[upper] == group_arr[lower])
        agree = inside & (level_arr[lower] - level_arr[upper] == 1)
        clash = inside & ~agree
        support = np.bincount(upper[agree], count[agree], n_lines) + np.bincount(
            lower[agree], count[agree], n_lines
        )
        against = np.bincount(upper[clash], count[clash], n_lines) + np.bincount(
            lower[clash], count[clash], n_lines
        )
        contested = ~excluded & (against > 0) & (against >= max_conflict * support)
        if attempt == 4 or not np.any(contested):
            break
        excluded |= contested
    rejected = int(count[clash].sum())
    # normalise each component's order to start at 0, number components by size
    roots, comp = np.unique(group_arr, return_inverse=True)
    lowest = np.full(roots.size, np.iinfo(np.int64).max)
    np.minimum.at(lowest, comp, level_arr)
    comp_size = np.bincount(comp, weights=sizes, minlength=roots.size)
    rank = np.empty(roots.size, dtype=np.int64)
    rank[np.lexsort((np.arange(roots.size), -comp_size))] = np.arange(roots.size)
    return LineOrder(
        order=(level_arr - lowest[comp]).astype(np.int32),
        component=rank[comp].astype(np.int32),
        rejected=rejected,
        contested=int(excluded.sum()),
    )


class HierarchicalLineOrder(Stage[Lines, OrderedLines]):
    """Lines in their topological order, longest mutual neighbourhoods first.

    Two lines are neighbours where one lies directly above the other in a column; the pairs
    with the longest neighbourhood are ordered first, every line once, contradicting pairs are
    rejected; lines that cannot be linked form separate components.

    The option ``end_overlaps_link`` off (tried as version 2, not adopted): two lines that
    overlap only by their ends over fewer than ``min_link`` columns are not neighbours
    (:func:`end_overlaps`): along a waistband's corner, such staircases of the skin's and
    the cloth's lines linked cloth lines one line off into the back's order. It caught 30
    of 111 wrong peaks on the tuning frames and none on fresh held-out ones, for 0.004-0.012
    point of the back (under long hair, line pieces overlap by their ends too).

    Version 3: a column's pair of lines is a neighbourhood only where its gap is at most
    1.3 times the mean of the gaps directly above and below it (``gap_ratio``; version 1:
    1.6). A line spacing changes slowly down a column, so a gap of 1.3-1.6 spacings is a
    line hidden where the depth steps (a waistband's edge hides the skin's line, and the
    cloth's next line shows 1.5 spacings below the skin's last), not a neighbour; counted
    as one, it ordered the cloth's lines a level off, which the numbering then refused
    as a block or numbered a line off.
    """

    name: ClassVar[str] = "order.hierarchical"
    stage: ClassVar[str] = "order"
    version: ClassVar[str] = "3"
    input_type = Lines
    output_type = OrderedLines

    class Params(StageParams):
        """Parameters of :class:`HierarchicalLineOrder`."""

        gap_ratio: float = Field(
            1.3,
            gt=1,
            description="Largest row gap of a neighbourhood relative to the gaps around it "
            "(version 1: 1.6; a wider gap hides a line).",
        )
        min_overlap: int = Field(
            3, ge=1, description="Least neighbourhood (columns) considered at all."
        )
        min_link: int = Field(
            6, ge=1, description="Least neighbourhood (columns) that links lines by itself."
        )
        max_conflict: float = Field(
            0.5, gt=0, description="Contradicting/supporting columns that leave a line out."
        )
        end_overlaps_link: bool = Field(
            True,
            description="Lines overlapping only by their ends over fewer than min_link "
            "columns are neighbours (off: the staircase option, tried as version 2).",
        )

    def run(self, data: Lines, params: Params, context: StageContext) -> OrderedLines:
        """Order the lines of ``data``; no lines give empty tables."""
        result = order_lines(
            data.col,
            data.row,
            data.line_id,
            gap_ratio=params.gap_ratio,
            min_overlap=params.min_overlap,
            min_link=params.min_link,
            max_conflict=params.max_conflict,
            end_overlaps_link=params.end_overlaps_link,
        )
        lid = data.line_id
        table = np.append(result.order, -1).astype(np.int32)
        order = table[np.where(lid >= 0, lid, -1)]
        return OrderedLines.extend(
            data,
            order=order,
            line_order=result.order,
            line_component=result.component,
        )
