"""Consecutive numbers two line spacings apart in their column: a line skipped between them.

With a code whose light lines are much dimmer than its heavy ones (35:65), a dark cloth
shows the heavy lines only: line search finds no peak of the light lines between them, and
line sequence analysis orders two heavy lines as neighbours, so that the block below a
waistband is numbered whole lines off (on the window-8 tuning twin of the held-out raster,
a scene's two cloth lines numbered 121 and 122 where they are 123 and 125; every window the
code reads there is too short to object). Their column gives them away: the two lines lie
two spacings apart while the lines above them in the same column lie one apart.

A pair of column neighbours numbered ``n`` and ``n + 1`` whose gap is at least ``ratio``
times the median of the single gaps beside it in the column (up to ``side`` on either side,
numbers within ``reach``; at least ``min_refs`` of them) is refused, both peaks (the column
does not tell which one is off), and a line with ``min_peaks`` such peaks or more, making
up ``line_share`` of its numbered peaks, is refused whole: its number is one for all its
columns, and its other columns lie where the line skipped is not found at all.
"""

from __future__ import annotations

import numpy as np

__all__ = ["consecutive_pairs", "skipped_line_gaps", "skipped_lines"]


def consecutive_pairs(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    *,
    side: int = 3,
    reach: int = 8,
    min_refs: int = 2,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Column neighbours numbered ``n`` and ``n + 1``, their gaps and the gaps beside them.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    side, reach, min_refs : int
        As :func:`skipped_line_gaps`.

    Returns
    -------
    upper, lower : numpy.ndarray
        int64 peak indices of every pair (consecutive numbered peaks of a column).
    gap : numpy.ndarray
        float64 row gap of every pair.
    median : numpy.ndarray
        float64 median of the gaps of up to ``side`` pairs on either side in the column
        (numbers within ``reach``); inf with fewer than ``min_refs``.
    """
    number = np.asarray(number)
    idx = np.flatnonzero(number >= 0)
    a, b = idx[:-1], idx[1:]
    keep = (col[a] == col[b]) & (number[b].astype(np.int64) - number[a] == 1)
    a, b = a[keep], b[keep]
    gap = (row[b] - row[a]).astype(np.float64)
    if a.size == 0 or side < 1:
        return a, b, gap, np.full(a.size, np.inf)
    from .check_scans import single_gap_medians  # compiled; the numba import costs ~0.3 s

    median = single_gap_medians(
        np.asarray(col[a], dtype=np.int64), np.asarray(number[a], dtype=np.int64), gap,
        side, reach, min_refs,
    )  # fmt: skip
    return a, b, gap, median


def skipped_line_gaps(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    *,
    ratio: float = 1.9,
    side: int = 3,
    reach: int = 8,
    min_refs: int = 2,
) -> np.ndarray:
    """Numbered peaks of consecutive numbers lying a skipped line apart in their column.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    ratio : float
        Least gap, in medians of the single gaps beside it, that refuses a pair.
    side : int
        Single gaps taken on either side of a pair in its column.
    reach : int
        Largest difference of numbers between the pair and a gap beside it.
    min_refs : int
        Fewest single gaps beside a pair for it to be judged.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for both peaks of every refused pair.
    """
    out = np.zeros(col.size, dtype=bool)
    a, b, gap, median = consecutive_pairs(
        col, row, number, side=side, reach=reach, min_refs=min_refs
    )
    judged = np.isfinite(median)
    skipped = judged & (gap >= ratio * median)
    out[a[skipped]] = True
    out[b[skipped]] = True
    return out


def skipped_lines(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    *,
    ratio: float = 1.9,
    side: int = 3,
    reach: int = 8,
    min_refs: int = 2,
    min_peaks: int = 3,
    line_share: float = 0.2,
) -> np.ndarray:
    """The peaks of :func:`skipped_line_gaps` and the lines made of enough of them.

    Parameters
    ----------
    col, row, line_id : numpy.ndarray
        Peaks sorted by ``(col, row)``; ``line_id`` -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    ratio, side, reach, min_refs
        As :func:`skipped_line_gaps`.
    min_peaks : int
        Fewest refused peaks of a line that refuse its other numbered peaks too (0: never).
    line_share : float
        Least share of a line's numbered peaks that those must make up.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    number = np.asarray(number)
    refused = skipped_line_gaps(
        col, row, number, ratio=ratio, side=side, reach=reach, min_refs=min_refs
    )
    lid = np.asarray(line_id, dtype=np.int64)
    if min_peaks <= 0 or not np.any(refused & (lid >= 0)):
        return refused
    n_lines = int(lid.max()) + 1
    hits = np.bincount(lid[refused & (lid >= 0)], minlength=n_lines)
    numbered = np.bincount(lid[(number >= 0) & (lid >= 0)], minlength=n_lines)
    whole = (hits >= min_peaks) & (hits >= line_share * np.maximum(numbered, 1))
    in_whole = np.append(whole, False)[np.where(lid >= 0, lid, -1)]
    return refused | (in_whole & (number >= 0))
