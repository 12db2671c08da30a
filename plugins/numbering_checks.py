"""Geometric evidence between components of ordered lines, for line numbering.

Line sequence analysis leaves lines that it cannot link in separate components; each gets
its absolute number from the code on its own. Two kinds of contact between components tell
how their numbers must relate, without the code:

* **column neighbours**: in a pixel column, the lowest peak of a line of component A lies
  directly above a peak of component B, at the local line spacing (the gap agrees with the
  gaps above and below it within ``gap_tolerance``). On a continuous surface these are two
  consecutive raster lines, so ``number(B line) = number(A line) + 1``. Any other relation
  is a depth step of a whole line spacing (or more) between touching surfaces, or an order
  that contradicts the image.
* **continuations**: a line of B starts a few columns (``max_gap``) after a line of A ends,
  where A's line, extended along its slope, arrives (within ``row_tolerance`` of the
  spacing) and B's line, extended backwards, arrives at A's end: one raster line
  interrupted by a shadow, a fold or the chin, so ``number(B line) = number(A line)``.

Both are returned as votes on the offset difference ``offset(B) - offset(A)`` of the two
components (offsets index the raster's lines at level 0), with a weight in columns.
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np

from rasterserver.raster import Raster
from rasterserver.records_lines import OrderedLines

from .code_evidence import robust_centres

__all__ = [
    "by_line",
    "column_order_conflicts",
    "contact_votes",
    "line_runs",
    "local_spacing",
    "numbered_peaks",
    "pair_contradictions",
    "plausible_distance",
    "unordered_pairs",
]


def contact_votes(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    line_order: np.ndarray,
    line_component: np.ndarray,
    *,
    gap_tolerance: float = 0.2,
    max_gap: int = 40,
    row_tolerance: float = 0.3,
    min_line: int = 5,
    continuation_weight: float = 4.0,
) -> dict[tuple[int, int], dict[int, float]]:
    """Votes on the offset differences of touching components.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_order, line_component : numpy.ndarray
        Per-line level and component (-1: unordered).
    gap_tolerance : float
        A column neighbour's gap may depart from the spacing by this fraction.
    max_gap : int
        Largest gap (columns) bridged by a continuation.
    row_tolerance : float
        Largest departure (in line spacings) of an extended line from the other's end.
    min_line : int
        Least peaks of each line of a continuation.
    continuation_weight : float
        Weight (in column-neighbour columns) of one continuation.

    Returns
    -------
    dict
        ``votes[(a, b)][delta]``: the weight of the evidence that
        ``offset(b) - offset(a) == delta``, for components ``a != b`` (both directions).
    """
    votes: dict[tuple[int, int], dict[int, float]] = defaultdict(lambda: defaultdict(float))
    n = col.size
    n_lines = line_order.size
    if n < 2 or n_lines < 2:
        return votes
    # compiled loops over the peaks and the line ends (contact_tallies); the numba import
    # costs ~0.3 s, hence here
    from .column_pairs import peak_levels
    from .contact_tallies import column_neighbours, continuations, level_gaps, line_ends

    comp, lev = peak_levels(line_id, line_order, line_component)
    # Typical spacing: the median gap between consecutive levels of one component.
    inside = level_gaps(col, row, comp, lev)
    spacing = float(np.median(inside)) if inside.size else float("nan")
    if not np.isfinite(spacing) or spacing <= 0:
        return votes
    # ---- column neighbours across two components: one vote per column, tallied per
    # (a, b, delta) in the order of each tally's first column
    comp_a, comp_b, deltas, count = column_neighbours(col, row, comp, lev, spacing, gap_tolerance)
    for a, b, d, m in zip(
        comp_a.tolist(), comp_b.tolist(), deltas.tolist(), count.tolist(), strict=True
    ):
        votes[(a, b)][d] += float(m)
        votes[(b, a)][-d] += float(m)
    # ---- continuations of lines across short gaps
    c0, c1, r0, r1, s0, s1, count = line_ends(col, row, line_id, n_lines, 8)
    ok = (count >= min_line) & (line_component >= 0) & (line_order >= 0)
    ends = np.flatnonzero(ok)
    if ends.size < 2:
        return votes
    tol = row_tolerance * spacing
    first, then = continuations(ends, line_component, c0, c1, r0, r1, s0, s1, max_gap, tol)
    pairs = zip(first.tolist(), then.tolist(), strict=True)
    for a, b in pairs:
        ca, cb = int(line_component[a]), int(line_component[b])
        delta = int(line_order[a] - line_order[b])
        w = continuation_weight * min(1.0, min(count[a], count[b]) / 20.0)
        votes[(ca, cb)][delta] += w
        votes[(cb, ca)][-delta] += w
    return votes


def plausible_distance(
    data: OrderedLines,
    mine: np.ndarray,
    levels: np.ndarray,
    offset: int,
    raster: Raster,
    station: Any,
    max_depth: float,
) -> str:
    """Empty when the points of the lines ``mine``, numbered with ``offset``, lie in the station's
    working volume (within ``max_depth`` mm of the calibrated distance); else the reason."""
    lid_all = data.line_id.astype(np.int64)
    idx = np.flatnonzero((lid_all >= 0) & mine[np.maximum(lid_all, 0)])
    if idx.size == 0:
        return ""
    idx = idx[:: max(1, idx.size // 64)]
    lid = data.line_id[idx].astype(np.int64)
    j = offset + levels[lid]
    if np.any(j < 0) or np.any(j >= raster.n_lines):
        return "numbers outside the raster"
    pix = np.column_stack([data.col[idx].astype(np.float64), data.row[idx]])
    try:
        pts = station.triangulate(pix, raster.positions[j])
        centre = np.asarray(station.camera.centre, dtype=np.float64)
    except Exception:  # a calibration without a usable model: the test is not made
        return ""
    good = np.all(np.isfinite(pts), axis=1)
    if not np.any(good):
        return "no point reconstructs with these numbers"
    dist = float(np.median(np.linalg.norm(pts[good] - centre, axis=1)))
    d0 = float(np.linalg.norm(centre))  # the world origin lies on the calibrated back plane
    if abs(dist - d0) > max_depth:
        return f"implausible distance ({dist:.0f} mm from the camera, calibrated {d0:.0f} mm)"
    return ""


def column_order_conflicts(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    *,
    tolerance: float = 0.3,
    max_multiple: int = 3,
    spacing: np.ndarray | None = None,
) -> np.ndarray:
    """Peaks whose number breaks the order of their column: two consecutive numbered peaks
    one line spacing apart (within ``tolerance`` spacings) whose numbers do not differ by
    exactly one, or ``m`` spacings apart (``2 <= m <= max_multiple``) whose numbers differ by
    more than ``m``, or any two close peaks numbered out of order; and, against the single
    gaps directly above and below them in their own column, numbers ``k`` apart less than
    ``k - 1/2`` of the smaller or more than ``k + 1/2`` of the wider gap apart. Both are
    refused: the image cannot tell which of the two is wrong. ``spacing`` is the per-peak local line
    spacing (:func:`local_spacing`) when the caller has it already."""
    n = col.size
    out = np.zeros(n, dtype=bool)
    if n < 2:
        return out
    # the pairs and the checks compiled (column_order); the numba import costs ~0.3 s
    from .column_order import numbered_pairs, order_conflicts

    a, b, gap, k = numbered_pairs(col, row, number)
    if a.size == 0 or not np.any(k == 1):
        return out
    # the local spacing: mean gap of consecutive lines in cells of 32 x 32 px
    if spacing is None:
        spacing = local_spacing(col, row, number)
    if spacing is None:
        return out
    # One spacing apart, the numbers must differ by one. Two or three spacings apart (lines
    # between unnumbered), they must not differ by more: a line picked up across a depth
    # step of a whole spacing shows as a pair two spacings apart numbered three apart. (They
    # may differ by less: the surface stretches the spacing towards a silhouette.) Against
    # the gaps beside it in its own column (the cell's mean spacing is too coarse where
    # lines crowd towards a silhouette): numbers k apart need about k gaps of the single
    # steps above and below; a line's end that took the neighbouring line's peak shows as
    # numbers two apart at one gap. And numbers k apart more than k + 1/2 of the wider gap
    # beside them apart: a line skipped between them that the numbers do not count (a
    # piece numbered a level off below a gap where lines went unfound).
    return order_conflicts(n, a, b, gap, k, spacing, tolerance, max_multiple)


def unordered_pairs(col: np.ndarray, row: np.ndarray, number: np.ndarray) -> np.ndarray:
    """Both peaks of every two numbered column neighbours whose numbers do not increase
    downwards (equal, or decreasing).

    A continuous surface shows the raster's lines in their order down a column, and where
    one surface hides another the hidden lines are skipped, not reordered, unless a
    surface overhangs one far behind it by more than the lines it hides (an occiput over
    the neck could): on the tuning frames no right numbering held such a pair (4,075
    clinic scenes), whatever the gap between them. The column does not tell which of the
    two is off, and refusing both is the safe side of the rare overhang.
    :func:`column_order_conflicts` judges the pairs within a few spacings of each other
    while the numbering is built; this is the order the last steps must leave (a line's
    first peak carried onto another surface's line below a peak a later step numbered).

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for both peaks of every such pair, and of the pairs that
        refusing them leaves out of order.
    """
    out = np.zeros(col.size, dtype=bool)
    if col.size < 2:
        return out
    from .column_order import numbered_pairs  # compiled; the numba import costs ~0.3 s

    left = np.asarray(number).copy()
    # refusing a pair makes the peaks beside it neighbours, which may be out of order in
    # turn (100, 105, 98, 99 leaves 100, 99): judged again until none is
    while True:
        a, b, _, k = numbered_pairs(col, row, left)
        bad = k <= 0
        if not np.any(bad):
            return out
        out[a[bad]] = True
        out[b[bad]] = True
        left[out] = -1


def pair_judgements(
    col: np.ndarray,
    area: np.ndarray,
    line_id: np.ndarray,
    line_number: np.ndarray,
    raster: Raster,
    lam: float,
    *,
    min_columns: int = 5,
    min_z: float = 3.0,
    min_departure: float = 0.75,
    correlation: float = 4.0,
    shifted: bool = False,
) -> tuple[np.ndarray, ...]:
    """Every pair of numbered lines, direct column neighbours numbered as consecutive raster
    lines, judged: does their intensity ratio contradict the kinds the code gives them?

    The numbering of a component rests on the ratios of all its level pairs; a short piece
    placed a level or two off (a cloth line across a waistband whose depth step is close to a
    whole spacing) hardly moves them. Judged pair by pair, the piece's ratios with its column
    neighbours (``log(area above / area below)``, robust centre over the shared columns) depart
    from the expected ``(kind above - kind below) * lam``.

    Parameters
    ----------
    col, area, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_number : numpy.ndarray
        ``(n_lines,)`` absolute number of every line, -1 when unnumbered.
    raster : Raster
        The code.
    lam : float
        ``log`` of the heavy/light area ratio.
    min_columns : int
        Fewest shared columns for a pair to be judged.
    min_z : float
        Least departure, in standard errors of the centre, that contradicts.
    min_departure : float
        Least departure, in units of ``lam``, that contradicts.
    correlation : float
        Columns over which the albedo texture is correlated (for the standard error).
    shifted : bool
        Also return ``moved``.

    Returns
    -------
    upper, lower, columns : numpy.ndarray
        Every pair's line ids (the upper line, the lower one) and the number of columns
        where they are neighbours.
    departure, z : numpy.ndarray
        How far the pair's ratio departs from the code's, in units of ``lam`` and in
        standard errors of the ratio's centre.
    contradicts : numpy.ndarray
        Bool: the pair contradicts the code (judged over ``min_columns`` columns or more).
    moved : numpy.ndarray
        ``(P, 2)`` the departure (units of ``lam``) were both lines numbered one less, one
        more (NaN beyond the code); only with ``shifted``.
    """
    empty = np.zeros(0, dtype=np.int64)
    nothing: tuple[np.ndarray, ...] = (empty, empty, empty, np.zeros(0), np.zeros(0))
    nothing += (np.zeros(0, dtype=bool),) + (np.zeros((0, 2)),) * shifted
    n = col.size
    if n < 2 or line_number.size == 0 or raster.n_lines < 2:
        return nothing
    # the pairs and their grouping in compiled loops (column_pairs); the numba import costs
    # ~0.3 s, hence here
    from .column_pairs import grouped_pairs, raster_pair_ratios

    lid = line_id.astype(np.int64)
    # each line's index into the raster's lines (-1: unnumbered)
    lut = np.full(int(raster.numbers.max()) + 2, -1, dtype=np.int64)
    lut[raster.numbers] = np.arange(raster.n_lines)
    num = line_number.astype(np.int64)
    pos_line = np.where((num >= 0) & (num < lut.size - 1), lut[np.clip(num, 0, lut.size - 1)], -1)
    # consecutive raster lines are two lines (a line has one number)
    a, ratio = raster_pair_ratios(col, area, line_id, pos_line)
    if a.size == 0:
        return nothing
    with np.errstate(divide="ignore", invalid="ignore"):
        lr = np.log(ratio)
    good = np.isfinite(lr)
    a, lr = a[good], np.clip(lr[good], -1.0, 1.0)
    if a.size == 0:
        return nothing
    b = a + 1
    code = raster.code.astype(np.float64)
    upper = pos_line[lid[a]]  # the lower peak's line is the next raster line
    expected = (code[upper] - code[upper + 1]) * lam
    keys, inv = grouped_pairs(lid[a], lid[b], int(lid.max()) + 1)
    # the robust centre of code_evidence.level_statistics (every pair has a column: the
    # groups are 0 .. keys.size - 1, all present)
    _, centre, counts, spread = robust_centres(inv, lr)
    exp_pair = np.zeros(keys.size)
    exp_pair[inv] = expected
    se = np.maximum(1.25 * spread / np.sqrt(np.maximum(counts / correlation, 1.0)), 0.01)
    departure = np.abs(centre - exp_pair)
    bad = (counts >= min_columns) & (departure >= min_departure * lam) & (departure >= min_z * se)
    span = int(lid.max()) + 1
    if not shifted:
        return keys // span, keys % span, counts, departure / lam, departure / se, bad
    # the departures were both lines numbered one less / one more (a block placed off)
    up_pair = np.zeros(keys.size, dtype=np.int64)
    up_pair[inv] = upper
    moved = np.full((keys.size, 2), np.nan)
    for k, s in enumerate((-1, 1)):
        p = up_pair + s
        ok = (p >= 0) & (p + 1 < code.size)
        q = np.clip(p, 0, code.size - 2)
        moved[:, k] = np.where(ok, np.abs(centre - (code[q] - code[q + 1]) * lam) / lam, np.nan)
    return keys // span, keys % span, counts, departure / lam, departure / se, bad, moved


def pair_contradictions(
    col: np.ndarray,
    area: np.ndarray,
    line_id: np.ndarray,
    line_number: np.ndarray,
    raster: Raster,
    lam: float,
    **thresholds: Any,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pairs of :func:`pair_judgements` (same parameters, ``thresholds`` its keywords)
    whose intensity ratio contradicts the code.

    Returns
    -------
    upper, lower, columns : numpy.ndarray
        The contradicting pairs' line ids (the upper line, the lower one) and the number of
        columns where they are neighbours.
    """
    judged = pair_judgements(col, area, line_id, line_number, raster, lam, **thresholds)
    upper, lower, columns, bad = judged[0], judged[1], judged[2], judged[5]
    return upper[bad], lower[bad], columns[bad]


def local_spacing(col: np.ndarray, row: np.ndarray, number: np.ndarray) -> np.ndarray | None:
    """Per peak, the mean row gap of consecutive numbered lines in its 32 x 32 px cell (the
    median over the frame where the cell has none); None without any such pair."""
    from .column_order import cell_spacing, numbered_pairs  # compiled; numba costs ~0.3 s

    a, _, gap, k = numbered_pairs(col, row, number)
    one = k == 1
    if not np.any(one):
        return None
    a, gap = a[one], gap[one]
    # dense cell indices (a frame has a few hundred cells), the gaps added pair by pair
    return cell_spacing(col, row, a, gap, float(np.median(gap)))


def by_line(lid: np.ndarray) -> np.ndarray:
    """Indices ordering peaks (sorted by column) by line (or any non-negative id), keeping
    the column order within a line: a stable sort, by radix on 16-bit ids when they fit
    (twelve times faster).

    Parameters
    ----------
    lid : numpy.ndarray
        Non-negative ids, one per peak.

    Returns
    -------
    numpy.ndarray
        The stable sorting permutation.
    """
    if lid.size and int(lid.max()) < 65536 and int(lid.min()) >= 0:
        return np.argsort(lid.astype(np.uint16), kind="stable")
    return np.argsort(lid, kind="stable")


def line_runs(lid: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Peaks ``idx`` line by line, in column order, and where each line starts and stops.

    Parameters
    ----------
    lid : numpy.ndarray
        int64 line of every peak (peaks sorted by column); non-negative at ``idx``.
    idx : numpy.ndarray
        Indices of the peaks taken.

    Returns
    -------
    order : numpy.ndarray
        ``idx`` ordered by line, each line's peaks in column order.
    starts, stops : numpy.ndarray
        Each line's first position in ``order`` and the position after its last.
    """
    order = idx[by_line(lid[idx])]
    lines = lid[order]
    starts = np.flatnonzero(np.r_[True, lines[1:] != lines[:-1]]) if order.size else order[:0]
    return order, starts, np.r_[starts[1:], order.size][: starts.size]


def numbered_peaks(
    col: np.ndarray, row: np.ndarray, line_id: np.ndarray, number: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The peaks' columns, rows, lines and numbers as the line-end checks read them.

    Parameters
    ----------
    col, row, line_id, number : numpy.ndarray
        Per peak (any integer or float dtypes).

    Returns
    -------
    col, row, line_id, number : numpy.ndarray
        int64, float64, int64 and int64.
    """
    return (
        np.asarray(col, dtype=np.int64),
        np.asarray(row, dtype=np.float64),
        np.asarray(line_id, dtype=np.int64),
        np.asarray(number, dtype=np.int64),
    )
