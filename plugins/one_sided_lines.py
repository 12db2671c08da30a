"""Short numbered lines that no column confirms from both sides.

A numbered line's number is confirmed in a column where numbered peaks lie directly above
and below it: the column order check then judges it between two neighbours. A short line
whose every numbered peak has a numbered neighbour on one side only is numbered by its
contact with that one neighbour: over a few columns its own code (the light/heavy kind of
a handful of peaks) decides nothing, and nothing beyond it confirms the count. Where it
lies on another surface than its neighbour, an arm or a cloth standing off the back by
about a line's depth, the surface shows the next raster line at the row where the
neighbour's order puts this one: on the clinic tuning scenes a cloth's 4-peak line under
a waistband and an arm's 7-peak line above the shoulder's line were numbered one off so.
Long lines are left alone: their kind is read over many peaks, and the top and bottom
lines of a back are one-sided over their whole length. Lines of up to five peaks are
judged (``one_sided_peaks``): up to seven took the arm's line too, for four times the
back's coverage (``docs/numbering-versions.md``, version 21).
"""

from __future__ import annotations

import numpy as np

from .peak_checks import numbered_column_neighbours

__all__ = ["one_sided_lines"]


def one_sided_lines(
    col: np.ndarray, line_id: np.ndarray, number: np.ndarray, *, max_peaks: int = 5
) -> np.ndarray:
    """The numbered peaks of short lines none of whose peaks is numbered between two others.

    Parameters
    ----------
    col : numpy.ndarray
        Column of every peak, peaks sorted by ``(col, row)``.
    line_id : numpy.ndarray
        Line of every peak, -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    max_peaks : int
        Longest line (numbered peaks) judged; 0 judges none.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    col = np.asarray(col)
    lid = np.asarray(line_id, dtype=np.int64)
    number = np.asarray(number)
    refused = np.zeros(number.size, dtype=bool)
    numbered = (number >= 0) & (lid >= 0)
    if max_peaks <= 0 or not np.any(numbered):
        return refused
    above, below = numbered_column_neighbours(col, number)
    n_lines = int(lid.max()) + 1
    peaks = np.bincount(lid[numbered], minlength=n_lines)
    confirmed = np.bincount(lid[numbered & above & below], minlength=n_lines)
    short = (peaks > 0) & (peaks <= max_peaks) & (confirmed == 0)
    refused[numbered] = short[lid[numbered]]
    return refused
