"""Scans of the peak checks down the columns and along the lines, compiled.

:func:`.peak_checks.beside_doubtful`, :func:`.peak_checks.doubtful_share`,
:func:`.peak_checks.column_islands` and :func:`.peak_checks.stranded_runs` were each a
dozen whole-array passes over all peaks (shifted copies, cumulative sums, run starts and
lengths, a sorted key searched for every candidate and column offset): ~1.2 ms of the
numbering's ~6 on a medium back, for checks that look at a peak's neighbours only. Here
each is one loop computing the same comparisons on the same float64 values; the decisions
are the same. :func:`misread_flags` reads the code down and up the columns for
:func:`.column_reading.misread_columns` and :func:`block_support_flags` reads each peak's
column pairs for :func:`.column_blocks.contradicted_blocks` (loops from the start).

Importing this module costs the numba import (~0.3 s): the peak checks import it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel

from .line_levels import union_root

__all__ = [
    "beside_flags",
    "block_roots",
    "block_support_flags",
    "doubtful_counts",
    "end_flags",
    "island_flags",
    "misread_flags",
    "single_gap_medians",
    "stranded_flags",
]


@kernel()
def _smaller(a: float, b: float) -> float:
    """``np.minimum`` of two floats: NaN when either is (Python's ``min`` depends on order)."""
    if a != a or b != b:
        return math.nan
    return a if a < b else b


@kernel()
def beside_flags(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    doubtful: np.ndarray,
    spacing: np.ndarray,
    max_gap: float,
) -> np.ndarray:
    """Numbered peaks with a doubtful column neighbour less than ``max_gap`` local spacings
    away (:func:`.peak_checks.beside_doubtful` without the share).

    Parameters
    ----------
    col : numpy.ndarray
        Column of every peak, peaks sorted by ``(col, row)``.
    row, spacing : numpy.ndarray
        float64 row and local line spacing of every peak.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    doubtful : numpy.ndarray
        bool, the doubtful peaks.
    max_gap : float
        Largest row gap, in local line spacings.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool.
    """
    n = col.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n - 1):
        if col[i] != col[i + 1]:
            continue
        if row[i + 1] - row[i] < max_gap * _smaller(spacing[i], spacing[i + 1]):
            if doubtful[i + 1]:
                out[i] = True
            if doubtful[i]:
                out[i + 1] = True
    for i in range(n):
        out[i] = out[i] and number[i] >= 0
    return out


@kernel()
def _first_at_least(key: np.ndarray, value: float, strictly: bool) -> int:
    """``np.searchsorted(key, value, side="right" if strictly else "left")``."""
    lo, hi = 0, key.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if key[mid] < value or (strictly and key[mid] == value):
            lo = mid + 1
        else:
            hi = mid
    return lo


@kernel()
def doubtful_counts(
    key: np.ndarray,
    col: np.ndarray,
    row: np.ndarray,
    at: np.ndarray,
    half: np.ndarray,
    doubtful: np.ndarray,
    numbered: np.ndarray,
    stride: float,
    reach: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Doubtful and numbered peaks in the square of half-width ``half`` around peaks ``at``
    (:func:`.peak_checks.doubtful_share`: the same sorted key, the same bounds).

    Parameters
    ----------
    key : numpy.ndarray
        float64 ``col * stride + row`` of every peak, ascending.
    col, row : numpy.ndarray
        Column and float64 row of every peak.
    at : numpy.ndarray
        int64 indices of the peaks counted around.
    half : numpy.ndarray
        float64 half-width of each square (px).
    doubtful, numbered : numpy.ndarray
        bool flags counted.
    stride : float
        The key's column stride.
    reach : int
        Largest column offset searched.

    Returns
    -------
    n_doubtful, n_numbered : numpy.ndarray
        int64 counts.
    """
    m = at.shape[0]
    n_doubtful = np.zeros(m, dtype=np.int64)
    n_numbered = np.zeros(m, dtype=np.int64)
    for j in range(m):
        p = at[j]
        lower = row[p] - half[j]
        upper = row[p] + half[j]
        for offset in range(-reach, reach + 1):
            if not abs(offset) <= half[j]:  # NaN: outside, as numpy compares
                continue
            centre = np.float64(col[p]) + np.float64(offset)
            lo = _first_at_least(key, centre * stride + lower, False)
            hi = _first_at_least(key, centre * stride + upper, True)
            for q in range(lo, hi):
                n_doubtful[j] += doubtful[q]
                n_numbered[j] += numbered[q]
    return n_doubtful, n_numbered


@kernel(error_model="numpy")
def island_flags(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray,
    min_peaks: int,
    min_gap: float,
) -> np.ndarray:
    """Numbered peaks in runs of fewer than ``min_peaks`` consecutive numbers standing
    ``min_gap`` local spacings apart from the column's other numbered peaks
    (:func:`.peak_checks.column_islands`).

    Parameters
    ----------
    col : numpy.ndarray
        Column of every peak, peaks sorted by ``(col, row)``.
    row, spacing : numpy.ndarray
        float64 row and local line spacing of every peak.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    min_peaks : int
        Least peaks of a run that stands alone.
    min_gap : float
        Gap, in local spacings, that makes a run stand alone.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool.
    """
    n = col.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    idx = np.flatnonzero(number >= 0)
    m = idx.shape[0]
    # gap[k]: rows from numbered peak k - 1 to k in the same column (inf across columns)
    gap = np.full(m + 1, np.inf)
    linked = np.zeros(m + 1, dtype=np.bool_)
    for k in range(1, m):
        p, q = idx[k - 1], idx[k]
        if col[q] == col[p]:
            gap[k] = row[q] - row[p]
            linked[k] = number[q] - number[p] == 1 and gap[k] < 1.5 * _smaller(
                spacing[q], spacing[p]
            )
    first = 0
    for k in range(1, m + 1):
        if k < m and linked[k]:
            continue
        last = k - 1
        above = gap[first] / spacing[idx[first]]
        below = gap[k] / spacing[idx[last]]
        if last - first + 1 < min_peaks and above >= min_gap and below >= min_gap:
            for j in range(first, last + 1):
                out[idx[j]] = True
        first = k
    return out


@kernel()
def stranded_flags(
    order: np.ndarray, line: np.ndarray, number: np.ndarray, min_run: int
) -> np.ndarray:
    """Numbered peaks in runs of fewer than ``min_run`` along their line beside a refused
    peak of the same line (:func:`.peak_checks.stranded_runs`).

    Parameters
    ----------
    order : numpy.ndarray
        int64 indices of the peaks in lines, line by line, each in column order.
    line : numpy.ndarray
        int64 line of each peak of ``order`` (in that order).
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered (indexed by peak).
    min_run : int
        Least length of a run kept beside refused peaks.

    Returns
    -------
    numpy.ndarray
        bool, one per peak (``number``'s length).
    """
    out = np.zeros(number.shape[0], dtype=np.bool_)
    m = order.shape[0]
    k = 0
    while k < m:
        if number[order[k]] < 0:
            k += 1
            continue
        first = k
        while k + 1 < m and line[k + 1] == line[k] and number[order[k + 1]] >= 0:
            k += 1
        last = k
        before = first > 0 and line[first - 1] == line[first]  # refused: else in the run
        after = last < m - 1 and line[last + 1] == line[last]
        if last - first + 1 < min_run and (before or after):
            for j in range(first, last + 1):
                out[order[j]] = True
        k += 1
    return out


@kernel()
def end_flags(
    order: np.ndarray,
    line: np.ndarray,
    number: np.ndarray,
    height: np.ndarray,
    min_refused: int,
    margin: int,
    dim_ratio: float,
    inner: int,
    jump: float,
) -> np.ndarray:
    """Numbered peaks at either end of a line's numbered peaks that the ends' evidence
    leaves in doubt (:func:`.peak_checks.line_ends`).

    Parameters
    ----------
    order : numpy.ndarray
        int64 indices of the peaks in lines, line by line, each in column order.
    line : numpy.ndarray
        int64 line of each peak of ``order`` (in that order).
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered (indexed by peak).
    height : numpy.ndarray
        float64 height of every peak (indexed by peak).
    min_refused, margin : int
        Beyond at least ``min_refused`` unnumbered peaks of the line, its first ``margin``
        numbered peaks are flagged (0: none).
    dim_ratio : float
        The end peak lower than this share of the mean height of the ``inner`` numbered
        peaks next to it is flagged (0: none).
    inner : int
        Numbered peaks the end peak is compared with; a line with fewer numbered peaks
        besides the end one is not judged on its height.
    jump : float
        The end peak higher than this many times, or lower than its inverse, the mean
        height of the two numbered peaks next to it is flagged (0: none).

    Returns
    -------
    numpy.ndarray
        bool, one per peak (``number``'s length).
    """
    out = np.zeros(number.shape[0], dtype=np.bool_)
    m = order.shape[0]
    start = 0
    while start < m:
        stop = start
        while stop + 1 < m and line[stop + 1] == line[start]:
            stop += 1
        # the line's numbered peaks, in column order, as positions in ``order``
        kept = np.empty(stop - start + 1, dtype=np.int64)
        k = 0
        for j in range(start, stop + 1):
            if number[order[j]] >= 0:
                kept[k] = j
                k += 1
        for side in range(2):
            if k == 0:
                break
            end = kept[0] if side == 0 else kept[k - 1]
            beyond = end - start if side == 0 else stop - end
            if margin > 0 and beyond >= min_refused:
                for t in range(min(margin, k)):
                    out[order[kept[t] if side == 0 else kept[k - 1 - t]]] = True
            if dim_ratio > 0 and k > inner:
                total = 0.0
                for t in range(1, inner + 1):
                    total += height[order[kept[t] if side == 0 else kept[k - 1 - t]]]
                if height[order[end]] < dim_ratio * total / inner:
                    out[order[end]] = True
            if jump > 0 and k >= 3:
                a, b = (1, 2) if side == 0 else (k - 2, k - 3)
                near = height[order[kept[a]]] + height[order[kept[b]]]
                e = height[order[end]]
                if e * jump < 0.5 * near or e > 0.5 * jump * near:
                    out[order[end]] = True
        start = stop + 1
    return out


@kernel()
def single_gap_medians(
    col: np.ndarray, number: np.ndarray, gap: np.ndarray, side: int, reach: int, min_refs: int
) -> np.ndarray:
    """Per pair of consecutive numbers in a column, the median of the gaps of up to ``side``
    such pairs on either side in its column (numbers within ``reach``); inf with fewer
    than ``min_refs`` (:func:`.skipped_lines.skipped_line_gaps`).

    Parameters
    ----------
    col, number, gap : numpy.ndarray
        Per pair (in peak order): column, the upper peak's number, the row gap.
    side, reach, min_refs : int
        As :func:`.skipped_lines.skipped_line_gaps`.

    Returns
    -------
    numpy.ndarray
        float64 per pair.
    """
    m = gap.shape[0]
    out = np.full(m, np.inf)
    refs = np.empty(2 * side)
    for i in range(m):
        count = 0
        for d in range(-side, side + 1):
            o = i + d
            if d == 0 or o < 0 or o >= m or col[o] != col[i]:
                continue
            if abs(np.int64(number[o]) - np.int64(number[i])) <= reach:
                # insertion into the sorted few (no array allocated per pair)
                j = count
                while j > 0 and refs[j - 1] > gap[o]:
                    refs[j] = refs[j - 1]
                    j -= 1
                refs[j] = gap[o]
                count += 1
        if count >= max(min_refs, 1):
            out[i] = 0.5 * (refs[(count - 1) // 2] + refs[count // 2])
    return out


@kernel()
def block_roots(
    col: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    upper: np.ndarray,
    lower: np.ndarray,
    col_gap: int,
    n_lines: int,
) -> np.ndarray:
    """Per numbered peak, a representative peak of its block (-1 unnumbered): the joined
    column pairs ``upper[k]``-``lower[k]`` and consecutive numbered peaks of one line and
    number at most ``col_gap`` columns apart, as one union-find pass
    (:func:`.detached_pieces.numbered_blocks`).

    Parameters
    ----------
    col, line_id, number : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    upper, lower : numpy.ndarray
        int64 peak indices of the joined column pairs.
    col_gap, n_lines : int
        Largest column step along a line; number of lines.

    Returns
    -------
    numpy.ndarray
        int64 per peak.
    """
    n = col.shape[0]
    parent = np.arange(n)
    for k in range(upper.shape[0]):
        a = union_root(parent, upper[k])
        b = union_root(parent, lower[k])
        if a != b:
            parent[max(a, b)] = min(a, b)
    last = np.full(n_lines, -1, dtype=np.int64)
    for i in range(n):
        line = line_id[i]
        if number[i] < 0 or line < 0:
            continue
        j = last[line]
        if j >= 0 and number[j] == number[i] and col[i] - col[j] <= col_gap:
            a = union_root(parent, i)
            b = union_root(parent, j)
            if a != b:
                parent[max(a, b)] = min(a, b)
        last[line] = i
    out = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        if number[i] >= 0:
            out[i] = union_root(parent, i)
    return out


@kernel()
def _run_costs(
    log_area: np.ndarray,
    run: np.ndarray,
    length: int,
    first: int,
    step: int,
    table: np.ndarray,
    shifts: int,
) -> tuple[float, float]:
    """The departure of a column run's log area ratios from the code's at its own numbers
    (``first``, ``first + step``, ...) and the least at another shift (inf where none fits
    inside the raster; NaN for the own numbers where they lie outside it)."""
    own = math.nan
    best = math.inf
    for shift in range(-shifts, shifts + 1):
        cost = 0.0
        valid = True
        for k in range(1, length):
            a = first + shift + step * (k - 1)
            b = first + shift + step * k
            if a < 0 or b < 0 or a >= table.size or b >= table.size:
                valid = False
                break
            expected = table[b] - table[a]
            if expected != expected:
                valid = False
                break
            cost += abs(log_area[run[k]] - log_area[run[k - 1]] - expected)
        if not valid:
            continue
        if shift == 0:
            own = cost
        elif cost < best:
            best = cost
    return own, best


@kernel()
def misread_flags(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    log_area: np.ndarray,
    table: np.ndarray,
    run_max: int,
    least: int,
    margin: float,
    clean: float,
    shifts: int,
) -> np.ndarray:
    """:func:`.column_reading.misread_columns` on int64 columns and numbers, float64 rows
    and log areas, and the raster's log widths by number (NaN: no such line)."""
    n = col.size
    flags = np.zeros(n, dtype=np.bool_)
    run = np.empty(run_max + 1, dtype=np.int64)
    for i in range(n):
        if number[i] < 0:
            continue
        for step in (1, -1):
            j = i + step
            other = i - step
            if j < 0 or j >= n or col[j] != col[i] or number[j] >= 0:
                continue
            if other < 0 or other >= n or col[other] != col[i] or number[other] < 0:
                continue
            gap = abs(row[i] - row[other])
            run[0] = i
            length = 1
            k = j
            while length <= run_max and 0 <= k < n and col[k] == col[i] and number[k] < 0:
                g = abs(row[k] - row[run[length - 1]])
                if g < 0.7 * gap or g > 1.4 * gap:
                    break
                run[length] = k
                length += 1
                gap = g
                k += step
            ratios = length - 1
            if ratios < least:
                continue
            own, best = _run_costs(log_area, run, length, number[i], step, table, shifts)
            if own != own or best == math.inf:
                continue
            if best <= clean * ratios and best + margin * ratios <= own:
                flags[i] = True
    return flags


@kernel()
def _pair_departure(
    number: np.ndarray, step: np.ndarray, k: int, table: np.ndarray, shift: int
) -> float:
    """The departure of column pair ``(k, k + 1)``'s log area ratio ``step[k]`` from the
    code's at their numbers shifted by ``shift`` (inf outside the raster or unreadable)."""
    lo = number[k] + shift
    hi = number[k + 1] + shift
    if min(lo, hi) < 0 or max(lo, hi) >= table.size:
        return math.inf
    departure = step[k] - (table[hi] - table[lo])
    if departure != departure:  # a NaN line width, or a zero area's -inf - -inf
        return math.inf
    return abs(departure)


@kernel()
def block_support_flags(
    number: np.ndarray,
    step: np.ndarray,
    pair: np.ndarray,
    table: np.ndarray,
    gain: float,
    clean: float,
    shifts: int,
    every: bool,
) -> np.ndarray:
    """The shifts each peak's column pairs support for
    :func:`.column_blocks.contradicted_blocks`: int64 numbers, float64 log area steps
    (``step[k]``: peak ``k + 1`` against ``k``), bool pairs, the raster's log widths;
    ``(n, 2 * shifts)`` bool, columns the shifts ``-shifts .. -1, 1 .. shifts`` (without
    ``every``, ``(n, 1)``: whether the peak supports any shift)."""
    n = number.size
    support = np.zeros((n, 2 * shifts if every else 1), dtype=np.bool_)
    for i in range(n):
        above = i >= 1 and bool(pair[i - 1])
        below = i < n - 1 and bool(pair[i])
        if not (above or below):
            continue
        per = (1.0 if above else 0.0) + (1.0 if below else 0.0)
        own = 0.0
        if above:
            own += _pair_departure(number, step, i - 1, table, 0)
        if below:
            own += _pair_departure(number, step, i, table, 0)
        if not own >= gain * per:  # no shift can gain that much
            continue
        for j in range(2 * shifts):
            shift = j - shifts if j < shifts else j - shifts + 1
            cost = 0.0
            if above:
                cost += _pair_departure(number, step, i - 1, table, shift)
            if below:
                cost += _pair_departure(number, step, i, table, shift)
            if cost <= clean * per and own - cost >= gain * per:
                support[i, j if every else 0] = True
                if not every:
                    break
    return support
