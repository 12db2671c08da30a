"""Scans along the chains of linked peaks of the line search, compiled.

The chain order, the corner cuts, the area steps and the running mean of
:mod:`.line_search` were each a dozen whole-array passes over the chain-ordered peaks
(shifted copies, accumulated chain bounds, cumulative sums, masks): ~1.5 ms of the line
search's ~4. Here each is one or two loops computing the same expressions in the same
order (the cumulative sums added peak by peak as ``np.cumsum`` added them); the area
steps' logarithm stays numpy's. The lines are the same.

Importing this module costs the numba import (~0.3 s): the line search imports it on use.
"""

from __future__ import annotations

import math

import numpy as np

from rasterserver.compiled import kernel


@kernel()
def chain_order(head: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Chain order of peaks from their chain heads: ``perm`` (position → peak) and each
    position's chain head.

    Parameters
    ----------
    head : numpy.ndarray
        int64 chain head of every peak (a link advances one column).
    col : numpy.ndarray
        Column of every peak.

    Returns
    -------
    perm, head_at : numpy.ndarray
        int64: chains one after the other in the order of their heads, each from its head.
    """
    n = head.shape[0]
    length = np.zeros(n, dtype=np.int64)
    for i in range(n):
        length[head[i]] += 1
    start = np.empty(n, dtype=np.int64)
    total = 0
    for i in range(n):
        start[i] = total
        total += length[i]
    perm = np.empty(n, dtype=np.int64)
    for i in range(n):
        perm[start[head[i]] + (np.int64(col[i]) - np.int64(col[head[i]]))] = i
    head_at = np.empty(n, dtype=np.int64)
    for k in range(n):
        head_at[k] = head[perm[k]]
    return perm, head_at


@kernel(error_model="numpy")
def corner_cuts(r: np.ndarray, linked: np.ndarray, corner: float) -> np.ndarray:
    """Links (by position ``k``: between ``k - 1`` and ``k``) that make a sharp corner: the
    row step departs by more than ``corner`` from the mean of the steps beside it, and
    more than its neighbours' do (only the worst link of a kink).

    Parameters
    ----------
    r : numpy.ndarray
        float64 rows in chain order.
    linked : numpy.ndarray
        bool: position ``k`` continues the chain of ``k - 1``.
    corner : float
        Largest departure (px).

    Returns
    -------
    numpy.ndarray
        bool per position.
    """
    return _local_peaks(_corner_departures(r, linked), corner)


@kernel(error_model="numpy")
def _corner_departures(r: np.ndarray, linked: np.ndarray) -> np.ndarray:
    """Per link, how far its row step departs from the mean of the steps beside it (0
    where it or both neighbours are no link)."""
    n = r.shape[0]
    step = np.empty(n)
    for k in range(n):
        s = 0.0 if k == 0 else r[k] - r[k - 1]
        step[k] = s if linked[k] else np.nan
    dev = np.empty(n)
    for k in range(n):
        prev_step = step[k - 1] if k >= 1 else np.nan
        next_step = step[k + 1] if k + 1 < n else np.nan
        if math.isnan(prev_step):
            around = next_step
        elif math.isnan(next_step):
            around = prev_step
        else:
            around = 0.5 * (prev_step + next_step)
        d = abs(step[k] - around)
        dev[k] = 0.0 if math.isnan(d) else d
    return dev


@kernel()
def _local_peaks(dev: np.ndarray, limit: float) -> np.ndarray:
    """Positions whose ``dev`` exceeds ``limit`` and is not below either neighbour's."""
    n = dev.shape[0]
    out = np.empty(n, dtype=np.bool_)
    for k in range(n):
        prev_dev = dev[k - 1] if k >= 1 else 0.0
        next_dev = dev[k + 1] if k + 1 < n else 0.0
        out[k] = dev[k] > limit and dev[k] >= prev_dev and dev[k] >= next_dev
    return out


@kernel()
def _bounds(linked: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last position of the chain of every position."""
    n = linked.shape[0]
    first = np.empty(n, dtype=np.int64)
    last = np.empty(n, dtype=np.int64)
    running = 0
    for k in range(n):
        running = max(running, 0 if linked[k] else k)
        first[k] = running
    running = n
    for k in range(n - 1, -1, -1):
        end = k == n - 1 or not linked[k + 1]
        running = min(running, k if end else n)
        last[k] = running
    return first, last


@kernel()
def _running_sums(a: np.ndarray) -> np.ndarray:
    """``total[k]``: the sum of ``a[:k]``, added as ``np.cumsum`` adds."""
    n = a.shape[0]
    total = np.zeros(n + 1)
    for k in range(n):
        total[k + 1] = a[k] if k == 0 else total[k] + a[k]
    return total


@kernel()
def turn_cuts(r: np.ndarray, linked: np.ndarray, turn: float, half: int) -> np.ndarray:
    """Links (by position ``k``: between ``k - 1`` and ``k``) where the chain turns: the
    mean row step of the ``half`` links before departs from that of the ``half`` links
    after by more than ``turn`` (only the worst link of a turn).

    A corner spread over two or three links (one surface's line running into another's,
    rounded by the peaks at the contour) departs little at each link from the steps beside
    it; the course before and after the contour still differ.

    Parameters
    ----------
    r : numpy.ndarray
        float64 rows in chain order.
    linked : numpy.ndarray
        bool: position ``k`` continues the chain of ``k - 1``.
    turn : float
        Largest change of the mean row step (px per column).
    half : int
        Links on each side.

    Returns
    -------
    numpy.ndarray
        bool per position.
    """
    n = r.shape[0]
    dev = np.zeros(n)
    for k in range(half, n - half):
        whole = True
        for j in range(k - half, k + half + 1):
            if not linked[j]:
                whole = False
                break
        if not whole:
            continue
        # steps k - half .. k - 1 (rows k - half - 1 .. k - 1) and k + 1 .. k + half
        before = (r[k - 1] - r[k - half - 1]) / half
        after = (r[k + half] - r[k]) / half
        dev[k] = abs(after - before)
    return _local_peaks(dev, turn)


@kernel()
def vertex_cuts(r: np.ndarray, linked: np.ndarray, cut: np.ndarray) -> np.ndarray:
    """``cut`` and, beside every cut link, the neighbouring link whose row step departs
    more from the steps beside it: the peak at the vertex leaves both chains.

    At a corner where one surface's line runs into another's, the peak at the vertex may
    belong to either line and the kink does not tell which; left on one side, it carries
    that line's number onto the other surface.

    Parameters
    ----------
    r : numpy.ndarray
        float64 rows in chain order.
    linked : numpy.ndarray
        bool: position ``k`` continues the chain of ``k - 1``.
    cut : numpy.ndarray
        bool: the links cut (corners, turns).

    Returns
    -------
    numpy.ndarray
        bool per position.
    """
    n = r.shape[0]
    dev = _corner_departures(r, linked)
    out = cut.copy()
    for k in range(n):
        if not cut[k]:
            continue
        best = -1
        for j in (k - 1, k + 1):
            free = 1 <= j < n and linked[j] and not cut[j]
            if free and (best < 0 or dev[j] > dev[best]):
                best = j
        if best >= 0:
            out[best] = True
    return out


@kernel(error_model="numpy")
def smooth_along(a: np.ndarray, linked: np.ndarray, half: int) -> np.ndarray:
    """Mean of ``a`` over ``±half`` positions of the same chain (chain-ordered arrays).

    Parameters
    ----------
    a : numpy.ndarray
        float64 values in chain order.
    linked : numpy.ndarray
        bool: position ``k`` continues the chain of ``k - 1``.
    half : int
        Half-width of the window, clipped to the chain.

    Returns
    -------
    numpy.ndarray
        float64 means.
    """
    n = a.shape[0]
    first, last = _bounds(linked)
    total = _running_sums(a)
    out = np.empty(n)
    for k in range(n):
        lo = max(k - half, first[k])
        hi = min(k + half, last[k])
        out[k] = (total[hi + 1] - total[lo]) / (hi - lo + 1)
    return out


@kernel(error_model="numpy")
def step_ratios(a: np.ndarray, linked: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """At every link, the mean of ``a`` over the ``half`` positions before against the
    ``half`` after (same chain), and whether both sides are full.

    Parameters
    ----------
    a : numpy.ndarray
        float64 values in chain order.
    linked : numpy.ndarray
        bool: position ``k`` continues the chain of ``k - 1``.
    half : int
        Positions on each side.

    Returns
    -------
    ratio, full : numpy.ndarray
        ``mean before / mean after`` (float64, inf or NaN at a chain's ends) and bool:
        linked with ``half`` positions on either side.
    """
    n = a.shape[0]
    first, last = _bounds(linked)
    total = _running_sums(a)
    ratio = np.empty(n)
    full = np.empty(n, dtype=np.bool_)
    for k in range(n):
        lo = max(k - half, first[k])  # before k: lo .. k - 1
        hi = min(k + half - 1, last[k])  # from k: k .. hi
        n_before = k - lo
        n_after = hi - k + 1
        before = (total[k] - total[lo]) / n_before
        after = (total[hi + 1] - total[k]) / n_after
        ratio[k] = before / after
        full[k] = linked[k] and n_before >= half and n_after >= half
    return ratio, full


@kernel()
def step_peaks(jump: np.ndarray, full: np.ndarray, log_ratio: float) -> np.ndarray:
    """Links whose area step exceeds ``log_ratio``, only the strongest of a step.

    Parameters
    ----------
    jump : numpy.ndarray
        ``|log(ratio)|`` of :func:`step_ratios`.
    full : numpy.ndarray
        :func:`step_ratios`'s ``full``.
    log_ratio : float
        The logarithm of the least area ratio cut.

    Returns
    -------
    numpy.ndarray
        bool per position.
    """
    n = jump.shape[0]
    j = np.empty(n)
    judged = np.empty(n, dtype=np.bool_)
    for k in range(n):
        judged[k] = full[k] and math.isfinite(jump[k])
        j[k] = jump[k] if judged[k] else 0.0
    out = np.empty(n, dtype=np.bool_)
    for k in range(n):
        prev_j = j[k - 1] if k >= 1 else 0.0
        next_j = j[k + 1] if k + 1 < n else 0.0
        out[k] = judged[k] and j[k] > log_ratio and j[k] >= prev_j and j[k] > next_j
    return out


@kernel()
def side_maxima(
    a: np.ndarray, head: np.ndarray, at: np.ndarray, step: int, window: int
) -> np.ndarray:
    """Largest ``a`` within ``window`` positions from each ``at`` in direction ``step``,
    same chain (positions past the ends clipped to them; 0 where none is of the chain).

    Parameters
    ----------
    a : numpy.ndarray
        float64 values in chain order.
    head : numpy.ndarray
        Chain head of every position.
    at : numpy.ndarray
        Positions searched from.
    step : int
        -1 (before) or 1 (after).
    window : int
        Positions searched.

    Returns
    -------
    numpy.ndarray
        float64 per ``at``.
    """
    n = a.shape[0]
    out = np.empty(at.shape[0])
    for i in range(at.shape[0]):
        best = -np.inf
        for j in range(1, window + 1):
            src = min(max(at[i] + step * j, 0), n - 1)
            v = a[src] if head[src] == head[at[i]] else 0.0
            if math.isnan(v):  # numpy's max propagates it
                best = v
                break
            if v > best or j == 1:
                best = v
        out[i] = best
    return out


@kernel()
def union_roots(parent: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Union-find roots of ``ids`` (-1 stays -1) in a forest whose roots are their own
    parents.

    Parameters
    ----------
    parent : numpy.ndarray
        int64 parent of every id.
    ids : numpy.ndarray
        int64 ids, -1 for none.

    Returns
    -------
    numpy.ndarray
        int64 roots.
    """
    out = np.empty_like(ids)
    for i in range(ids.shape[0]):
        x = ids[i]
        if x >= 0:
            while parent[x] != x:
                x = parent[x]
        out[i] = x
    return out
