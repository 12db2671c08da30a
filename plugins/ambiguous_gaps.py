"""Short lines numbered across a gap that lies between two counts of line spacings.

Where a line is numbered ``k`` from a numbered neighbour in its column, the gap between
them should be ``k`` line spacings (the single gap beyond the neighbour, in the same
column). Across a depth step, a waistband's cloth standing off the skin, the gap is no
whole number of spacings: at 1.5 spacings the image cannot tell whether one line or two
lie between, and the count that numbered the line is a guess. On the held-out raster's
tuning scene 213079 a cloth line below a waistband was numbered 130 from the skin's 129
across 1.5 spacings (and from 128 across 2.5), where it is 131: nine peaks one line off,
and nothing else on the line (60 peaks, the rest left unnumbered) to object.

A short line, of at most ``max_peaks`` numbered peaks, whose numbered peaks lie (median)
at least ``departure`` spacings off a whole count from their numbered column neighbours is
refused. Long lines are left alone: their number is read from their code over many peaks
and confirmed along their length.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ambiguous_gap_lines", "gap_departures"]


def gap_departures(col: np.ndarray, row: np.ndarray, number: np.ndarray) -> np.ndarray:
    """Per peak: how far its gap to the numbered peak next to it in its column lies off a
    whole count of line spacings.

    For a numbered peak ``p`` with a numbered column neighbour ``q`` (``k >= 1`` numbers
    apart, in order) and beyond ``q`` a numbered peak ``r`` one number from ``q``, the
    departure is ``|gap(p, q) / gap(q, r) - k|``; the larger of the two sides (above,
    below) where both are known.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` float64, NaN where no side is known.
    """
    col = np.asarray(col)
    row = np.asarray(row, dtype=np.float64)
    num = np.asarray(number, dtype=np.int64)
    n = num.size
    out = np.full(n, np.nan)
    for side in (1, -1):  # 1: the neighbour above (the previous peak), -1: below
        p = np.arange(n)
        q, r = p - side, p - 2 * side
        ok = (r >= 0) & (r < n) & (q >= 0) & (q < n)
        p, q, r = p[ok], q[ok], r[ok]
        ok = (col[p] == col[q]) & (col[q] == col[r])
        ok &= (num[p] >= 0) & (num[q] >= 0) & (num[r] >= 0)
        k = side * (num[p] - num[q])
        ok &= (k >= 1) & (side * (num[q] - num[r]) == 1)
        p, q, r, k = p[ok], q[ok], r[ok], k[ok]
        spacing = np.abs(row[q] - row[r])
        good = spacing > 0
        p, q, k, spacing = p[good], q[good], k[good], spacing[good]
        d = np.abs(np.abs(row[p] - row[q]) / spacing - k)
        out[p] = np.fmax(out[p], d)  # fmax: NaN on one side takes the other
    return out


def ambiguous_gap_lines(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    *,
    max_peaks: int = 20,
    departure: float = 0.4,
) -> np.ndarray:
    """The numbered peaks of short lines numbered across gaps no whole count of spacings
    explains (:func:`gap_departures`).

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_id : numpy.ndarray
        Line of every peak, -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    max_peaks : int
        Longest line (numbered peaks) judged; 0 judges none.
    departure : float
        Least median departure (in spacings) of the line's numbered peaks that refuses it.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    lid = np.asarray(line_id, dtype=np.int64)
    number = np.asarray(number)
    refused = np.zeros(number.size, dtype=bool)
    numbered = (number >= 0) & (lid >= 0)
    if max_peaks <= 0 or not np.any(numbered):
        return refused
    n_lines = int(lid.max()) + 1
    peaks = np.bincount(lid[numbered], minlength=n_lines)
    short = (peaks > 0) & (peaks <= max_peaks)
    judged = numbered & short[np.maximum(lid, 0)]
    if not np.any(judged):
        return refused
    dep = gap_departures(col, row, number)
    known = judged & np.isfinite(dep)
    # the median per line: sort the known departures by (line, departure)
    order = np.lexsort((dep[known], lid[known]))
    lines, dep_sorted = lid[known][order], dep[known][order]
    first = np.searchsorted(lines, np.arange(n_lines), side="left")
    count = np.bincount(lines, minlength=n_lines)
    median = np.full(n_lines, np.nan)
    has = count > 0
    lo = first[has] + (count[has] - 1) // 2
    hi = first[has] + count[has] // 2
    median[has] = 0.5 * (dep_sorted[lo] + dep_sorted[hi])
    with np.errstate(invalid="ignore"):
        off = has & (median >= departure)
    refused[judged] = off[lid[judged]]
    return refused
