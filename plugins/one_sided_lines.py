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

The same holds for a small component the code could not place and that inherited its
numbers from the components it touches (:func:`one_sided_components`, version 23): where
all it touches lies on one side of it, the count rests on that one boundary. On the twin
raster's tuning scenes 44000-44799 two such components of cloth below a waistband (3 and
22 peaks) were numbered one line off from the skin's lines above; no component numbered
from both sides erred.
"""

from __future__ import annotations

import numpy as np

from .peak_checks import numbered_column_neighbours

__all__ = ["one_sided_components", "one_sided_lines"]


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


def one_sided_components(
    col: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    line_component: np.ndarray,
    linked: np.ndarray,
    *,
    max_peaks: int = 50,
) -> np.ndarray:
    """The numbered peaks of small inherited components touched by numbered peaks of other
    components on one side only.

    A component's peak is touched from above (below) where the next peak up (down) its
    column is numbered and belongs to another component. A component of at most
    ``max_peaks`` numbered peaks that inherited its numbers (``linked``) is refused unless
    it is touched from above in one of its columns and from below in one.

    Parameters
    ----------
    col : numpy.ndarray
        Column of every peak, peaks sorted by ``(col, row)``.
    line_id : numpy.ndarray
        Line of every peak, -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    line_component : numpy.ndarray
        Component of every line.
    linked : numpy.ndarray
        ``(C,)`` bool: the components numbered by inheritance from the ones they touch.
    max_peaks : int
        Largest component (numbered peaks) judged; 0 judges none.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    lid = np.asarray(line_id, dtype=np.int64)
    number = np.asarray(number)
    refused = np.zeros(number.size, dtype=bool)
    linked = np.asarray(linked, dtype=bool)
    if max_peaks <= 0 or not np.any(linked) or number.size == 0:
        return refused
    comps = np.asarray(line_component, dtype=np.int64)
    comp = np.where(lid >= 0, comps[np.maximum(lid, 0)], -1)
    numbered = (number >= 0) & (comp >= 0)
    judged = numbered & np.append(linked, False)[np.where(comp >= 0, comp, -1)]
    if not np.any(judged):
        return refused
    col = np.asarray(col)
    same_col = col[1:] == col[:-1]
    # the next peak up and down each column: numbered, and of another component
    up = np.zeros(number.size, dtype=bool)
    down = np.zeros(number.size, dtype=bool)
    other = same_col & numbered[:-1] & numbered[1:] & (comp[:-1] != comp[1:])
    up[1:] = other
    down[:-1] = other
    n_comp = int(comps.max()) + 1 if comps.size else 0
    size = np.bincount(comp[judged], minlength=n_comp)
    from_above = np.bincount(comp[judged & up], minlength=n_comp) > 0
    from_below = np.bincount(comp[judged & down], minlength=n_comp) > 0
    one_sided = (size > 0) & (size <= max_peaks) & ~(from_above & from_below)
    refused[judged] = one_sided[comp[judged]]
    return refused
