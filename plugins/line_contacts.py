"""The column neighbourhoods of :func:`.line_sequence.line_neighbours`, compiled.

Each pair of consecutive peaks in a column was judged in some twenty whole-array passes
(the gaps above and below, the cells' typical gaps by two ``bincount`` rounds, the masks):
~0.8 ms of the order stage's ~1.9. Here one loop per pass over the peaks; the cells' sums
are added pair by pair as ``bincount`` added them, and the gaps are only compared, so the
neighbourhoods are the same.

Importing this module costs the numba import (~0.3 s): the order stage imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel(error_model="numpy")
def neighbour_keys(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    n_lines: int,
    gap_ratio: float,
    cell: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Keys ``upper * n_lines + lower`` of the column neighbourhoods, and of the skips.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``, rows finite, and their lines (-1: none).
    n_lines : int
        Number of lines.
    gap_ratio : float
        Largest gap of a neighbourhood against the gaps above and below it, and against
        the typical gap of its cell.
    cell : int
        Cell size (px) of the typical gap.

    Returns
    -------
    pairs, skips : numpy.ndarray
        int64 keys in peak order: of every neighbourhood column, and of every column where
        two lines follow each other with unlined peaks between them.
    """
    n = col.shape[0]
    m = max(n - 1, 0)
    gap = np.empty(m)
    same = np.empty(m, dtype=np.bool_)
    cell_row = np.empty(m, dtype=np.int64)
    inv_cell = 1.0 / cell
    top = 0
    for i in range(m):
        same[i] = col[i + 1] == col[i]
        gap[i] = row[i + 1] - row[i]
        cell_row[i] = np.int64(max(row[i], 0.0) * inv_cell)
        top = max(top, cell_row[i])
    # the typical gap of a cell: the mean gap, then the mean of the gaps up to 1.4 times it
    cell_id = np.empty(m, dtype=np.int64)
    n_cells = 0
    for i in range(m):
        cell_id[i] = (np.int64(col[i]) // cell) * (top + 1) + cell_row[i]
        if same[i]:
            n_cells = max(n_cells, cell_id[i] + 1)
    typical = np.full(n_cells, np.inf)
    total = np.zeros(n_cells)
    count = np.zeros(n_cells, dtype=np.int64)
    for i in range(m):
        if same[i]:
            total[cell_id[i]] += gap[i]
            count[cell_id[i]] += 1
    _means(total, count, typical)
    total[:] = 0.0
    count[:] = 0
    for i in range(m):
        if same[i] and gap[i] <= 1.4 * typical[cell_id[i]]:
            total[cell_id[i]] += gap[i]
            count[cell_id[i]] += 1
    _means(total, count, typical)
    pairs = np.empty(m, dtype=np.int64)
    n_pairs = 0
    for i in range(m):
        a, b = line_id[i], line_id[i + 1]
        if not same[i] or a < 0 or b < 0 or a == b:
            continue
        g_prev = gap[i - 1] if i >= 1 and same[i - 1] else np.nan
        g_next = gap[i + 1] if i + 1 < m and same[i + 1] else np.nan
        if math.isnan(g_prev):
            ref = gap[i] if math.isnan(g_next) else g_next
        else:
            ref = g_prev if math.isnan(g_next) else 0.5 * (g_prev + g_next)
        if gap[i] <= gap_ratio * ref and gap[i] <= gap_ratio * typical[cell_id[i]]:
            pairs[n_pairs] = np.int64(a) * n_lines + b
            n_pairs += 1
    skips = np.empty(m, dtype=np.int64)
    n_skips = 0
    last = -1
    for i in range(n):
        if line_id[i] < 0:
            continue
        if last >= 0 and col[i] == col[last] and i - last > 1 and line_id[last] != line_id[i]:
            skips[n_skips] = np.int64(line_id[last]) * n_lines + line_id[i]
            n_skips += 1
        last = i
    return pairs[:n_pairs], skips[:n_skips]


@kernel(error_model="numpy")
def _means(total: np.ndarray, count: np.ndarray, out: np.ndarray) -> None:
    """``out`` = ``total / count`` where ``count`` > 0, else inf."""
    for c in range(total.shape[0]):
        out[c] = total[c] / max(count[c], 1) if count[c] > 0 else np.inf
