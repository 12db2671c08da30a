"""A line's end peaks that are the outermost of their column, where the gap to the next
line grows.

Where a shoulder, an arm or a cloth's edge begins, the first or last peaks of a line often
have nothing above (or below) them in their column: the line is the column's outermost,
and only its own continuity and the one neighbour on the other side carry its number. If
the line runs there onto another surface (an arm raised a line's depth in front of the
trunk, the trunk's line hidden behind it), the other surface's line takes the row of the
hidden one and the line search links it smoothly, but the gap to the neighbouring line
changes: the two lie on surfaces at different depths. Along one surface a line's gap to
its neighbour changes slowly, a few per cent over a few columns.

On the tuning frames of BENCHMARKS.md "Real bodies" (44) (clinic rasters 210000-211199
and the held-out raster's 211200-211599, peaks version 6), 4 of the 15 wrongly numbered
peaks are such outermost end peaks whose gap to the next peak in their column is 1.24-1.48
times the line's gap further in; of the 2.3 million right end peaks (the three outermost
numbered of each end) about one in a thousand is so (a fraction of a thousandth of the
back's crossings).
"""

from __future__ import annotations

import numpy as np

from .numbering_checks import line_runs, numbered_peaks

__all__ = ["outer_ends"]


def _column_gaps(col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each peak's gap (rows) to the next peak above and below it in its column (NaN: none).

    Peaks are sorted by ``(col, row)``, so a column's neighbours are adjacent.
    """
    above = np.full(col.size, np.nan)
    below = np.full(col.size, np.nan)
    if col.size > 1:
        same = col[1:] == col[:-1]
        gap = row[1:] - row[:-1]
        above[1:][same] = gap[same]
        below[:-1][same] = gap[same]
    return above, below


def outer_ends(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    *,
    gap_ratio: float = 1.2,
    depth: int = 3,
    inner: int = 4,
) -> np.ndarray:
    """The numbered end peaks of lines that are the outermost of their column and lie
    farther from the next peak than the line does further in.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_id : numpy.ndarray
        Line of every peak, -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    gap_ratio : float
        Least ratio of the end peak's gap to the next peak in its column (on its one
        side holding any) over the median of the same side's gaps of the line's ``inner``
        numbered peaks next further in; 0 judges none.
    depth : int
        Numbered peaks judged at each end, from the outermost in; the first not refused
        stops the end's judgement.
    inner : int
        Numbered peaks after those whose gaps give the line's own; lines of fewer than
        ``depth + inner`` numbered peaks are not judged.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    col, row, lid, number = numbered_peaks(col, row, line_id, number)
    refused = np.zeros(number.size, dtype=bool)
    numbered = np.nonzero((number >= 0) & (lid >= 0))[0]
    if gap_ratio <= 0 or numbered.size == 0 or depth < 1 or inner < 1:
        return refused
    above, below = _column_gaps(col, row)
    idx, starts, ends = line_runs(lid, numbered)
    long_enough = (ends - starts) >= depth + inner
    for first, stop in zip(starts[long_enough], ends[long_enough], strict=True):
        seq = idx[first:stop]
        for end_seq in (seq, seq[::-1]):  # each end, its outermost peak first
            reference = end_seq[depth : depth + inner]
            for k in range(depth):
                e = end_seq[k]
                if np.isnan(above[e]) and not np.isnan(below[e]):
                    gap, own = below[e], below[reference]
                elif np.isnan(below[e]) and not np.isnan(above[e]):
                    gap, own = above[e], above[reference]
                else:
                    break  # not the column's outermost, or alone in it
                own = own[~np.isnan(own)]
                if own.size == 0 or gap <= gap_ratio * float(np.median(own)):
                    break
                refused[e] = True
    return refused
