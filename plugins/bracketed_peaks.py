"""Peaks bracketed in their column by numbered ones: numbered by counting the lines between.

The numbering decides numbers by component and line, and the peak checks then refuse
whatever the image leaves in doubt. Some peaks stay unnumbered although their column alone
settles their number: in the hair over the upper back lines break into fragments too short
to read the code, and a check refuses a peak for what its *line* does (a jump, a
neighbouring doubtful line). Where such a run of ``m`` unnumbered peaks lies between a
numbered peak ``n`` above and a numbered peak ``n + m + 1`` below, and every one of the
``m + 1`` gaps is one line spacing, there is exactly one line per gap: the run holds the
lines ``n + 1 .. n + m``, whatever their lines did elsewhere. A depth step hiding a line
would leave a gap of a different size or a count that does not add up, so nothing is
numbered there.

On the clinic tuning scenes (``benchmarks/real_bodies.py``, seeds 7000-8199) this numbered
no peak wrongly and covered 0.19-0.23 point more of the back (version 8 of the numbering).

The count can still add up wrongly: a line hidden behind a depth step and a spurious peak
(an arm's edge, a fold) in the same column make ``m`` peaks in ``m + 1`` gaps of one
spacing, and the run is numbered one line off. The peaks' own lines then say so: they
carry other numbers where they are numbered. With ``line_id`` a run is left unnumbered
when any of its peaks lies on a line whose numbered peaks carry another number than the
count gives it (``bracket_line``, version 30 of the numbering: on section (44)'s held-out
scene 212733 two peaks on the back proper, below an arm; on fresh frames it refused six
peaks of 1,600 scenes and changed nothing else, BENCHMARKS.md "Real bodies" (45)).
"""

from __future__ import annotations

import numpy as np

__all__ = ["bracketed_numbers", "fill_brackets"]


def bracketed_numbers(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray,
    *,
    max_run: int = 8,
    tolerance: float = 0.2,
    line_id: np.ndarray | None = None,
) -> np.ndarray:
    """Numbers for the unnumbered peaks bracketed in their column by numbered peaks.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    spacing : numpy.ndarray
        Per-peak local line spacing (:func:`.numbering_checks.local_spacing`); NaN where
        unknown.
    max_run : int
        Longest run of unnumbered peaks between two numbered ones that is numbered.
    tolerance : float
        Largest departure of every gap of the run from one line spacing (the mean of the
        two bracketing peaks' spacings), as a fraction of it.
    line_id : numpy.ndarray, optional
        Per-peak line (-1: none). When given, a run is left unnumbered if one of its peaks
        lies on a line whose numbered peaks carry another number than the run gives it.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` int32: ``number`` with the bracketed peaks numbered.
    """
    out = np.asarray(number, dtype=np.int32).copy()
    n = col.size
    if n < 3 or max_run < 1:
        return out
    col = np.asarray(col, dtype=np.int64)
    row = np.asarray(row, dtype=np.float64)
    numbered = np.flatnonzero(out >= 0)
    if numbered.size < 2:
        return out
    a, b = numbered[:-1], numbered[1:]
    m = b - a - 1  # unnumbered peaks between consecutive numbered ones (sorted by column, row)
    keep = (m >= 1) & (m <= max_run) & (col[a] == col[b])
    keep &= out[b].astype(np.int64) - out[a] == m + 1
    a, b, m = a[keep], b[keep], m[keep]
    if a.size == 0:
        return out
    with np.errstate(invalid="ignore"):
        step = 0.5 * (np.asarray(spacing, dtype=np.float64)[a] + spacing[b])
        fits = np.isfinite(step) & (step > 0)
        gap = np.diff(row)  # gap[i]: peak i to peak i + 1 (same column inside a bracket)
        for j in range(int(m.max()) + 1):
            inside = j <= m
            g = gap[np.minimum(a + j, n - 2)]
            fits &= ~inside | (np.abs(g - step) <= tolerance * step)
    a, m = a[fits], m[fits]
    if line_id is not None and a.size:
        keep = _lines_agree(out, np.asarray(line_id, dtype=np.int64), a, m)
        a, m = a[keep], m[keep]
    for j in range(1, int(m.max(initial=0)) + 1):
        sel = m >= j
        out[a[sel] + j] = out[a[sel]] + j
    return out


def _lines_agree(
    number: np.ndarray, line_id: np.ndarray, a: np.ndarray, m: np.ndarray
) -> np.ndarray:
    """Per run (starting after peak ``a``, ``m`` peaks long): whether no peak's line carries
    another number than the run's count gives the peak."""
    n_lines = int(line_id.max(initial=-1)) + 1
    if n_lines == 0:
        return np.ones(a.size, dtype=bool)
    numbered = (number >= 0) & (line_id >= 0)
    low = np.full(n_lines, np.iinfo(np.int64).max)
    high = np.full(n_lines, -1, dtype=np.int64)
    np.minimum.at(low, line_id[numbered], number[numbered])
    np.maximum.at(high, line_id[numbered], number[numbered])
    agree = np.ones(a.size, dtype=bool)
    for j in range(1, int(m.max(initial=0)) + 1):
        inside = m >= j
        peak = a[inside] + j
        lid = line_id[peak]
        given = number[a[inside]].astype(np.int64) + j
        carried = lid >= 0
        carried[carried] &= high[lid[carried]] >= 0
        other = carried.copy()
        other[carried] = (low[lid[carried]] != given[carried]) | (
            high[lid[carried]] != given[carried]
        )
        agree[np.flatnonzero(inside)[other]] = False
    return agree


def fill_brackets(
    col: np.ndarray,
    row: np.ndarray,
    number: np.ndarray,
    spacing: np.ndarray | None,
    max_run: int,
    tolerance: float,
    line_id: np.ndarray | None = None,
) -> tuple[np.ndarray, str]:
    """:func:`bracketed_numbers`, and the note for the numbering's reason.

    Parameters
    ----------
    col, row, number : numpy.ndarray
        As in :func:`bracketed_numbers`.
    spacing : numpy.ndarray or None
        Per-peak local line spacing; None (no numbered pair anywhere) numbers nothing.
    max_run, tolerance, line_id
        As in :func:`bracketed_numbers`.

    Returns
    -------
    number : numpy.ndarray
        ``(N,)`` int32, the bracketed peaks numbered.
    note : str
        "N unnumbered peak(s) numbered ...", or "" when none was.
    """
    if spacing is None:
        return np.asarray(number, dtype=np.int32), ""
    filled = bracketed_numbers(
        col, row, number, spacing, max_run=max_run, tolerance=tolerance, line_id=line_id
    )
    added = int(np.count_nonzero(filled != number))
    if not added:
        return filled, ""
    return filled, (
        f"{added} unnumbered peak(s) numbered by counting the line spacings to numbered "
        "peaks above and below them in their column"
    )
