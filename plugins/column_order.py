"""Numbered peaks in their columns: the local spacing and the order check, compiled.

:func:`.numbering_checks.local_spacing` and :func:`.numbering_checks.column_order_conflicts`
took the pairs of consecutive numbered peaks in a column, their gaps and the gaps beside
them in some thirty whole-array passes (masks, gathers, shifted copies): ~1.5 ms of the
numbering's ~10. Here each is a loop over the peaks or the pairs, with the same expressions
in the same order: the per-cell sums are added pair by pair as ``bincount`` added them, and
the order check only compares, so its refusals are the same.

Importing this module costs the numba import (~0.3 s): the checks import it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def numbered_pairs(
    col: np.ndarray, row: np.ndarray, number: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Consecutive numbered peaks (in peak order) that share a column.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak number (-1: unnumbered).

    Returns
    -------
    a, b, gap, k : numpy.ndarray
        The upper and lower peak of every pair, ``row[b] - row[a]`` and
        ``number[b] - number[a]`` (int64).
    """
    n = col.shape[0]
    a = np.empty(max(n - 1, 0), dtype=np.int64)
    b = np.empty_like(a)
    gap = np.empty(a.shape[0])
    k = np.empty_like(a)
    m = 0
    last = -1
    for i in range(n):
        if number[i] < 0:
            continue
        if last >= 0 and col[last] == col[i]:
            a[m], b[m] = last, i
            gap[m] = row[i] - row[last]
            k[m] = np.int64(number[i]) - np.int64(number[last])
            m += 1
        last = i
    return a[:m], b[:m], gap[:m], k[:m]


@kernel(error_model="numpy")
def cell_spacing(
    col: np.ndarray, row: np.ndarray, a: np.ndarray, gap: np.ndarray, fallback: float
) -> np.ndarray:
    """Per peak, the mean gap of the pairs whose upper peak lies in its 32 x 32 px cell.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``; rows finite.
    a, gap : numpy.ndarray
        Upper peak and row gap of every pair of consecutive lines.
    fallback : float
        The spacing of a cell without a pair.

    Returns
    -------
    numpy.ndarray
        float64 per peak.
    """
    n = col.shape[0]
    top = 0.0
    for i in range(n):
        top = max(top, row[i])  # np.max(row, initial=0.0) for finite rows
    n_rows = np.int64(top) // 32 + 1
    cell_of = np.empty(n, dtype=np.int64)
    n_cells = 0
    for i in range(n):
        cell_of[i] = (np.int64(col[i]) // 32) * n_rows + np.int64(max(row[i], 0.0)) // 32
        n_cells = max(n_cells, cell_of[i] + 1)
    total = np.zeros(n_cells)
    count = np.zeros(n_cells, dtype=np.int64)
    for j in range(a.shape[0]):
        total[cell_of[a[j]]] += gap[j]
        count[cell_of[a[j]]] += 1
    mean = np.empty(n_cells)
    for c in range(n_cells):
        mean[c] = total[c] / max(count[c], 1) if count[c] > 0 else fallback
    out = np.empty(n)
    for i in range(n):
        out[i] = mean[cell_of[i]]
    return out


@kernel()
def _minimum(x: float, y: float) -> float:
    """``np.minimum``: NaN when either is."""
    if math.isnan(x) or math.isnan(y):
        return math.nan
    return x if x <= y else y


@kernel(error_model="numpy")
def order_conflicts(
    n: int,
    a: np.ndarray,
    b: np.ndarray,
    gap: np.ndarray,
    k: np.ndarray,
    spacing: np.ndarray,
    tolerance: float,
    max_multiple: int,
) -> np.ndarray:
    """Peaks whose numbers break the order of their column (as
    :func:`.numbering_checks.column_order_conflicts` describes).

    Parameters
    ----------
    n : int
        Number of peaks.
    a, b, gap, k : numpy.ndarray
        The pairs of :func:`numbered_pairs`.
    spacing : numpy.ndarray
        Per-peak local line spacing.
    tolerance : float
        Departure (in spacings) from a whole number of spacings still counted as one.
    max_multiple : int
        Largest number of spacings checked.

    Returns
    -------
    numpy.ndarray
        ``(n,)`` bool.
    """
    out = np.zeros(n, dtype=np.bool_)
    m_pairs = a.shape[0]
    for i in range(m_pairs):
        ref = spacing[a[i]]
        steps = gap[i] / ref
        m = np.rint(steps)
        near = m <= max_multiple and abs(steps - m) <= tolerance
        conflict = (near and m == 1 and k[i] != 1) or (near and m >= 2 and k[i] > m)
        conflict = conflict or (k[i] <= 0 and gap[i] < 1.5 * ref)
        # the single gaps directly above and below in the column (inf: none)
        above = math.inf
        if i > 0 and b[i - 1] == a[i] and k[i - 1] == 1:
            above = gap[i - 1]
        below = math.inf
        if i + 1 < m_pairs and b[i] == a[i + 1] and k[i + 1] == 1:
            below = gap[i + 1]
        beside = _minimum(above, below)
        conflict = conflict or (
            k[i] >= 2 and math.isfinite(beside) and gap[i] < (k[i] - 0.5) * beside
        )
        widest = max(above if math.isfinite(above) else 0.0, below if math.isfinite(below) else 0.0)
        conflict = conflict or (k[i] >= 1 and widest > 0 and gap[i] > (k[i] + 0.5) * widest)
        if conflict:
            out[a[i]] = True
            out[b[i]] = True
    return out
