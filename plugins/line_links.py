"""The line search's scans, compiled with numba: peak links, chain heads, line ids.

:func:`rasterserver_plugins.line_search.search_lines` linked the peaks of adjacent columns,
followed the links to the chains' heads and relabelled the lines with whole-array passes
(binary searches, gathers, pointer jumping, two sorts in ``np.unique``): ~5 of its ~12 ms.
These loops read each peak a few times. They compute the same integers as those passes did
(the float keys and distances by the same expressions), so the plugin's results and version
do not change.

Importing this module costs the numba import (~0.3 s): the line search imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def mutual_links(
    col: np.ndarray, row: np.ndarray, span: float, max_step: float
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual-nearest-neighbour links between peaks of adjacent columns.

    Parameters
    ----------
    col : numpy.ndarray
        ``(N,)`` int64 peak columns, sorted by ``(col, row)`` with ``row``.
    row : numpy.ndarray
        ``(N,)`` float64 peak rows.
    span : float
        Key stride of a column (larger than any row difference plus ``max_step``).
    max_step : float
        Largest row step of a link (px).

    Returns
    -------
    right, left : numpy.ndarray
        ``(N,)`` int64 index of the linked peak in the next / previous column, -1 for none.
    """
    n = col.shape[0]
    key = np.empty(n)
    for i in range(n):
        key[i] = col[i] * span + row[i]
    nxt = np.full(n, -1, dtype=np.int64)
    ok = np.zeros(n, dtype=np.bool_)
    j = 0
    for i in range(n):
        target = col[i] + 1
        # np.searchsorted(key, t) ("left"), found by walking on from the previous query's
        # position: the queries ascend with the peaks (a binary search each cost 2 ms)
        t = target * span + row[i]
        if j > 0 and key[j - 1] >= t:
            j = int(np.searchsorted(key, t))
        while j < n and key[j] < t:
            j += 1
        best = -1
        dist = math.inf
        for c in (j - 1, j):
            if 0 <= c < n and col[c] == target:
                dd = abs(row[c] - row[i])
                if dd < dist:
                    best = c
                    dist = dd
        nxt[i] = best
        ok[i] = best >= 0 and dist <= max_step
    # Mutual: p must be the nearest to q = nxt[p] in p's column too. Rows are sorted within
    # a column, so that holds when neither of p's neighbours in its column is nearer to q.
    right = np.full(n, -1, dtype=np.int64)
    left = np.full(n, -1, dtype=np.int64)
    for p in range(n):
        if not ok[p]:
            continue
        q = nxt[p]
        d = abs(row[p] - row[q])
        mutual = True
        for nb in (p - 1, p + 1):
            if 0 <= nb < n and col[nb] == col[p] and abs(row[nb] - row[q]) <= d:
                mutual = False
        if mutual:
            right[p] = q
            left[q] = p
    return right, left


@kernel()
def chain_heads(left: np.ndarray) -> np.ndarray:
    """The first peak of every peak's chain (itself when it has no left link).

    ``left`` links each peak to one in the previous column, which comes earlier in
    ``(col, row)`` order, so one pass in that order finds every head.
    """
    n = left.shape[0]
    head = np.empty(n, dtype=np.int64)
    for i in range(n):
        if left[i] >= i:  # only unsorted peaks give a link to a later peak
            raise ValueError("peaks must be sorted by (col, row)")
        head[i] = head[left[i]] if left[i] >= 0 else i
    return head


@kernel()
def ranked_labels(label: np.ndarray, min_length: int) -> np.ndarray:
    """Line ids ranked by each line's first peak; lines under ``min_length`` peaks dropped.

    Parameters
    ----------
    label : numpy.ndarray
        ``(N,)`` int64 line label of every peak in peak order (-1: none).
    min_length : int
        Least number of peaks of a line.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` int32 ids ``0 .. L - 1`` in order of the lines' first peaks, -1 elsewhere.
    """
    n = label.shape[0]
    top = -1
    for i in range(n):
        top = max(top, label[i])
    counts = np.zeros(top + 1, dtype=np.int64)
    for i in range(n):
        if label[i] >= 0:
            counts[label[i]] += 1
    rank = np.full(top + 1, -1, dtype=np.int64)
    out = np.full(n, -1, dtype=np.int32)
    next_id = 0
    for i in range(n):
        v = label[i]
        if v >= 0 and counts[v] >= min_length:
            if rank[v] < 0:
                rank[v] = next_id
                next_id += 1
            out[i] = rank[v]
    return out
