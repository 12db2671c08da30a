"""The contacts between components of :func:`.numbering_checks.contact_votes`, compiled.

The column neighbours were found in some twenty whole-array passes over the peaks (masks,
the gaps above and below, their reference) and tallied by ``np.unique`` and a sort; the
line ends by a stable sort and masked least-squares windows; the continuations by a
blocked comparison of every line end with every line start: ~2.3 ms of the numbering's
~10. Here each is one loop over the peaks or the line ends. The expressions are the
same, in the same order (the end slopes' sums in numpy's pairwise order,
:mod:`.pairwise_sums`), so the votes are the same bits, entered in the same order.

Importing this module costs the numba import (~0.3 s): the numbering imports it on use.
"""

from __future__ import annotations

import math

import numpy as np
from numba import types
from numba.typed import Dict

from rasterserver.compiled import kernel

from .pairwise_sums import pairwise_sum


@kernel()
def level_gaps(col: np.ndarray, row: np.ndarray, comp: np.ndarray, lev: np.ndarray) -> np.ndarray:
    """Row gaps between consecutive levels of one component in a column, in peak order.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    comp, lev : numpy.ndarray
        Component and level of every peak (:func:`.column_pairs.peak_levels`).

    Returns
    -------
    numpy.ndarray
        float64 gaps (their median is the typical line spacing).
    """
    n = col.shape[0]
    out = np.empty(max(n - 1, 0))
    k = 0
    for i in range(n - 1):
        # consecutive levels of one component in a column
        same = col[i + 1] == col[i] and comp[i + 1] == comp[i] and comp[i] >= 0
        if same and lev[i + 1] == lev[i] + 1:
            out[k] = row[i + 1] - row[i]
            k += 1
    return out[:k]


_TALLY = types.UniTuple(types.int64, 3)


@kernel(error_model="numpy")
def column_neighbours(
    col: np.ndarray,
    row: np.ndarray,
    comp: np.ndarray,
    lev: np.ndarray,
    spacing: float,
    gap_tolerance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Column neighbours in two components at the local spacing, tallied.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    comp, lev : numpy.ndarray
        Component and level of every peak (:func:`.column_pairs.peak_levels`).
    spacing : float
        The typical line spacing (median of :func:`level_gaps`).
    gap_tolerance : float
        A neighbour's gap may depart from the spacing beside it by this fraction.

    Returns
    -------
    a, b, delta, count : numpy.ndarray
        int64 per (upper component, lower component, ``offset(b) - offset(a)``) seen, in
        the order of its first column, and the number of its columns.
    """
    n = col.shape[0]
    slot = Dict.empty(key_type=_TALLY, value_type=types.int64)  # (a, b, delta) -> output index
    a_out = np.empty(max(n - 1, 0), dtype=np.int64)
    b_out = np.empty_like(a_out)
    d_out = np.empty_like(a_out)
    count = np.zeros_like(a_out)
    n_out = 0
    for i in range(n - 1):
        if col[i + 1] != col[i] or comp[i] < 0 or comp[i + 1] < 0 or comp[i] == comp[i + 1]:
            continue
        gap = row[i + 1] - row[i]
        # the gaps of consecutive levels of one component directly above and below
        g_prev = np.nan
        j = i - 1
        same = j >= 0 and col[j + 1] == col[j] and comp[j + 1] == comp[j] and comp[j] >= 0
        if same and lev[j + 1] == lev[j] + 1:
            g_prev = row[i] - row[i - 1]
        g_next = np.nan
        j = i + 1
        same = j + 1 < n and col[j + 1] == col[j] and comp[j + 1] == comp[j] and comp[j] >= 0
        if same and lev[j + 1] == lev[j] + 1:
            g_next = row[i + 2] - row[i + 1]
        if math.isnan(g_prev):
            ref = spacing if math.isnan(g_next) else g_next
        else:
            ref = g_prev if math.isnan(g_next) else 0.5 * (g_prev + g_next)
        if not (abs(gap / ref - 1.0) <= gap_tolerance and abs(ref / spacing - 1.0) <= 0.5):
            continue
        key = (comp[i], comp[i + 1], lev[i] + 1 - lev[i + 1])
        if key in slot:
            s = slot[key]
        else:
            s = n_out
            slot[key] = s
            a_out[s], b_out[s], d_out[s] = key
            n_out += 1
        count[s] += 1
    return a_out[:n_out], b_out[:n_out], d_out[:n_out], count[:n_out]


@kernel(error_model="numpy")
def line_ends(
    col: np.ndarray, row: np.ndarray, line_id: np.ndarray, n_lines: int, fit: int
) -> tuple[np.ndarray, ...]:
    """Per line: first/last column and row, the slopes at both ends, and the peak count.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``; ``line_id`` below ``n_lines`` (-1: none).
    n_lines : int
        Number of lines.
    fit : int
        Peaks at either end of a line whose least-squares slope is taken (at least 3 of
        them, else the slope is 0).

    Returns
    -------
    c0, c1, r0, r1, s0, s1, count : numpy.ndarray
        As ``numbering_checks._line_ends`` (columns -1 and rows NaN for lines without
        peaks).
    """
    count = np.zeros(n_lines, dtype=np.int64)
    for i in range(line_id.shape[0]):
        if line_id[i] >= 0:
            count[line_id[i]] += 1
    # the peaks line by line, each line in column order (a counting sort: stable)
    starts = np.zeros(n_lines + 1, dtype=np.int64)
    for line in range(n_lines):
        starts[line + 1] = starts[line] + count[line]
    order = np.empty(starts[n_lines], dtype=np.int64)
    fill = starts[:n_lines].copy()
    for i in range(line_id.shape[0]):
        line = line_id[i]
        if line >= 0:
            order[fill[line]] = i
            fill[line] += 1
    c0 = np.full(n_lines, -1, np.int64)
    c1 = np.full(n_lines, -1, np.int64)
    r0 = np.full(n_lines, np.nan)
    r1 = np.full(n_lines, np.nan)
    s0 = np.zeros(n_lines)
    s1 = np.zeros(n_lines)
    xs = np.empty(fit)
    ys = np.empty(fit)
    terms = np.empty(fit)
    for line in range(n_lines):
        a, b = starts[line], starts[line + 1]
        if b == a:
            continue
        c0[line], c1[line] = col[order[a]], col[order[b - 1]]
        r0[line], r1[line] = row[order[a]], row[order[b - 1]]
        m = min(fit, b - a)
        if m < 3:
            continue
        s0[line] = _end_slope(col, row, order, a, m, xs, ys, terms)
        s1[line] = _end_slope(col, row, order, b - m, m, xs, ys, terms)
    return c0, c1, r0, r1, s0, s1, count


@kernel(error_model="numpy")
def _end_slope(
    col: np.ndarray,
    row: np.ndarray,
    order: np.ndarray,
    first: int,
    m: int,
    xs: np.ndarray,
    ys: np.ndarray,
    terms: np.ndarray,
) -> float:
    """Least-squares slope of the ``m`` peaks from ``order[first]``, as numpy took it: in a
    window of ``xs.size`` entries, those past ``m`` repeating the first peak at weight 0."""
    fit = xs.shape[0]
    for k in range(fit):
        p = order[first + k] if k < m else order[first]
        w = 1.0 if k < m else 0.0
        xs[k] = np.float64(col[p])
        ys[k] = row[p]
        terms[k] = xs[k] * w
    xm = pairwise_sum(terms, 0, fit) / m
    for k in range(fit):
        terms[k] = ys[k] * (1.0 if k < m else 0.0)
    ym = pairwise_sum(terms, 0, fit) / m
    for k in range(fit):
        dx = (xs[k] - xm) * (1.0 if k < m else 0.0)
        xs[k] = dx
        terms[k] = dx * dx
    den = pairwise_sum(terms, 0, fit)
    for k in range(fit):
        terms[k] = xs[k] * (ys[k] - ym)
    num = pairwise_sum(terms, 0, fit)
    return num / den if den > 0 else 0.0


@kernel(error_model="numpy")
def continuations(
    ends: np.ndarray,
    line_component: np.ndarray,
    c0: np.ndarray,
    c1: np.ndarray,
    r0: np.ndarray,
    r1: np.ndarray,
    s0: np.ndarray,
    s1: np.ndarray,
    max_gap: int,
    tol: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Line ends continued by exactly one line start of another component a few columns on.

    Parameters
    ----------
    ends : numpy.ndarray
        int64 lines judged, ascending.
    line_component : numpy.ndarray
        Per-line component.
    c0, c1, r0, r1, s0, s1 : numpy.ndarray
        Per-line ends (:func:`line_ends`).
    max_gap : int
        Largest gap (columns) bridged.
    tol : float
        Largest departure (rows) of an extended line from the other's end.

    Returns
    -------
    a, b : numpy.ndarray
        int64 lines: ``b`` continues ``a``; in the order of ``a`` in ``ends``.
    """
    n = ends.shape[0]
    a_out = np.empty(n, dtype=np.int64)
    b_out = np.empty(n, dtype=np.int64)
    k = 0
    for i in range(n):
        a = ends[i]
        hits = 0
        found = -1
        for j in range(n):
            b = ends[j]
            dc = np.int64(c0[b]) - np.int64(c1[a])
            if dc < 1 or dc > max_gap or line_component[b] == line_component[a]:
                continue
            dcc = np.float64(dc)
            fwd = r1[a] + s1[a] * dcc  # a extended to b's start
            bwd = r0[b] - s0[b] * dcc  # b extended back to a's end
            if abs(fwd - r0[b]) <= tol and abs(bwd - r1[a]) <= tol:
                hits += 1
                if found < 0:
                    found = b
        if hits == 1:  # none, or not unique: no evidence
            a_out[k] = a
            b_out[k] = found
            k += 1
    return a_out[:k], b_out[:k]
