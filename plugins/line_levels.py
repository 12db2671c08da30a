"""The line search's threshold levels, compiled: runs, seeds, splits and joins of lines.

:func:`rasterserver_plugins.line_search.search_lines` worked through its area thresholds
with a dozen whole-array passes per level over the still unlabelled peaks (masks, run
bounds, gathers, ``np.minimum.reduceat`` and ``np.unique`` for the runs' minima, the side
maxima and union-find roots, a Python loop over the lines joined) and a last pass of roots
and relabelling: ~1.5 ms of its ~2.8 on a frame, most of it the calls' overhead on a few
hundred runs. Here one loop per level walks the runs of free peaks and decides each as the
passes did, with the same comparisons on the same floats; the threshold levels' scale (the
median area) stays numpy's. The lines are the same; the levels take ~0.2 ms, the line
search 1.0 instead of 2.4 ms on the medium back (22,000 peaks).

Importing this module costs the numba import (~0.3 s): the line search imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def _chain_starts(linked: np.ndarray) -> np.ndarray:
    """First position of the chain of every position."""
    n = linked.shape[0]
    first = np.empty(n, dtype=np.int64)
    running = 0
    for k in range(n):
        running = max(running, 0 if linked[k] else k)
        first[k] = running
    return first


@kernel()
def _side_max(a: np.ndarray, first: np.ndarray, at: int, step: int, window: int) -> float:
    """Largest ``a`` within ``window`` positions from ``at`` in direction ``step``, same chain
    (positions past the array's ends clipped to them, 0 for positions of another chain)."""
    n = a.shape[0]
    best = -np.inf
    for j in range(1, window + 1):
        src = min(max(at + step * j, 0), n - 1)
        v = a[src] if first[src] == first[at] else 0.0
        if math.isnan(v):  # numpy's max propagates it
            return v
        if v > best or j == 1:
            best = v
    return best


@kernel()
def union_root(parent: np.ndarray, x: int) -> int:
    """Union-find root of ``x`` (-1 stays -1), halving the path walked (the roots stay).

    Parameters
    ----------
    parent : numpy.ndarray
        int64 parent of every element (a root is its own); shortened in place.
    x : int
        The element.

    Returns
    -------
    int
    """
    if x >= 0:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
    return x


@kernel()
def level_labels(
    a: np.ndarray,
    linked: np.ndarray,
    perm: np.ndarray,
    thresholds: np.ndarray,
    dip: float,
    dip_window: int,
    min_seed: int,
    min_length: int,
) -> np.ndarray:
    """Line label of every peak from the hierarchy of area thresholds.

    At each threshold, highest first, the runs of still unlabelled chained positions whose
    area reaches it are judged: a run touching no line becomes a new line when it has
    ``min_seed`` positions (``min_length`` at the last threshold); a run touching one line
    joins it; a run touching two lines is split at its weakest position when that lies
    below ``dip`` times the smaller of the two lines' largest areas within ``dip_window``
    positions (the weakest position then in neither line), else it and the two lines
    become one line. Lines are judged by their union-find roots at the level's start: the
    joins of a level take effect at the next.

    Parameters
    ----------
    a : numpy.ndarray
        float64 (smoothed) areas in chain order.
    linked : numpy.ndarray
        bool: position ``k`` continues the chain of ``k - 1``.
    perm : numpy.ndarray
        int64 peak of every position.
    thresholds : numpy.ndarray
        float64 area thresholds, highest first.
    dip : float
        Area ratio of a pronounced minimum.
    dip_window : int
        Positions searched on each side of a run for the lines' areas.
    min_seed, min_length : int
        Least positions of a new line before the last threshold / at it.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` int64 line label of every peak in peak order (the roots, not yet ranked
        or filtered by length), -1 for none.
    """
    n = a.shape[0]
    first = _chain_starts(linked)
    label = np.full(n, -1, dtype=np.int64)
    # every run of a level starts one line at most, and a position is in one run only
    parent = np.empty(n, dtype=np.int64)
    lines = 0
    todo = np.arange(n)
    n_todo = n
    free = np.empty(n, dtype=np.int64)
    join_x = np.empty(n, dtype=np.int64)
    join_y = np.empty(n, dtype=np.int64)
    n_levels = thresholds.shape[0]
    for li in range(n_levels):
        kept = 0
        for i in range(n_todo):
            if label[todo[i]] < 0:
                todo[kept] = todo[i]
                kept += 1
        n_todo = kept
        n_free = 0
        for i in range(n_todo):
            if a[todo[i]] >= thresholds[li]:
                free[n_free] = todo[i]
                n_free += 1
        need = min_length if li == n_levels - 1 else max(min_seed, min_length)
        n_joins = 0
        i0 = 0
        while i0 < n_free:
            i1 = i0 + 1
            while i1 < n_free and free[i1] == free[i1 - 1] + 1 and linked[free[i1]]:
                i1 += 1
            s = free[i0]
            e = free[i1 - 1]
            # a run's neighbours in its chain are not free at this level: their labels are
            # the previous levels', whichever run is labelled first
            left = label[max(s - 1, 0)] if linked[s] else -1
            right = label[e + 1] if e + 1 < n and linked[e + 1] else -1
            left = union_root(parent, left)
            right = union_root(parent, right)
            if left >= 0 and right >= 0 and left != right:
                cut = s  # the first of the run's weakest positions
                for p in range(s + 1, e + 1):
                    if a[p] < a[cut]:
                        cut = p
                before = _side_max(a, first, s, -1, dip_window)
                after = _side_max(a, first, e, 1, dip_window)
                if math.isnan(before) or math.isnan(after):  # np.minimum propagates it
                    side = math.nan
                else:
                    side = before if before < after else after
                if a[cut] < dip * side:
                    for p in range(s, e + 1):
                        label[p] = left if p < cut else (right if p > cut else -1)
                else:
                    for p in range(s, e + 1):
                        label[p] = left
                    join_x[n_joins] = left
                    join_y[n_joins] = right
                    n_joins += 1
            elif left >= 0 or right >= 0:
                lab = left if left >= 0 else right
                for p in range(s, e + 1):
                    label[p] = lab
            elif i1 - i0 >= need:
                # ids of new lines follow the existing ones, which the joins below keep
                parent[lines] = lines
                for p in range(s, e + 1):
                    label[p] = lines
                lines += 1
            i0 = i1
        # the joins after all runs are judged: a run's lines are its neighbours' roots at
        # the level's start
        for j in range(n_joins):
            x = union_root(parent, join_x[j])
            y = union_root(parent, join_y[j])
            if x != y:
                parent[max(x, y)] = min(x, y)
    out = np.full(n, -1, dtype=np.int64)
    for k in range(n):
        if label[k] >= 0:
            out[perm[k]] = union_root(parent, label[k])
    return out
