"""A line's numbered end peaks that follow the course of its refused peaks beyond them.

Where a trunk line runs on onto an arm or a cloth, the line search links the two surfaces'
lines into one, and the checks refuse the far part; the last numbered peaks before it are
the place where the surface changes, and nothing but the line's continuity carries their
number. The course of the line in the image tells where the change is: on one surface the
line runs straight over a few columns, and at the other surface's edge it turns. An end
peak that lies on the straight course of the refused peaks beyond it (within
``course_beyond`` rows) and off the course of its own line's numbered peaks farther in (by
``course_departure`` rows or more) lies on the refused surface, and is refused; from the
outermost peak inwards, up to three peaks.

On the clinic tuning frames rendered for version 27 (67400-68599, an AMD EPYC), four of
the nineteen wrongly numbered peaks were such ends (trunk lines run onto an arm, a cloth's
line onto the skin), and the rule refused about 1,400 right peaks in 1,200 scenes (0.005
point of the back's coverage). On fresh held-out frames (clinic rasters 69000-69999 and
88000-88199, the held-out raster 88200-88599; criteria written before) it removed none of
the 910 wrongly numbered peaks, so it is an option of the stage (``course_beyond``), off
(BENCHMARKS.md "Real bodies", 2026-12-01 (40)).
"""

from __future__ import annotations

import numpy as np

from .numbering_checks import line_runs, numbered_peaks

__all__ = ["turned_courses"]

# peaks beyond the end whose course is continued (fewer than the least: no course)
_BEYOND_MOST, _BEYOND_LEAST = 5, 3
# the end peaks judged, and the numbered peaks farther in whose course they are held to
_JUDGED, _INNER_MOST, _INNER_LEAST = 3, 6, 4


def _course(peaks: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Slope and intercept of the straight line fitted through the rows of ``peaks``."""
    return np.polyfit(col[peaks].astype(np.float64), row[peaks], 1)


def turned_courses(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    *,
    beyond: float = 0.4,
    departure: float = 1.0,
) -> np.ndarray:
    """The numbered end peaks of lines that lie on the course of the line's unnumbered
    peaks beyond them rather than on their own numbered peaks' course.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_id : numpy.ndarray
        Line of every peak, -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    beyond : float
        Largest distance (rows) of an end peak from the straight course of the three to
        five unnumbered peaks beyond it; 0 judges none.
    departure : float
        Least distance (rows) of an end peak from the straight course of the four to six
        numbered peaks farther in, past the three judged.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    col, row, lid, number = numbered_peaks(col, row, line_id, number)
    refused = np.zeros(number.size, dtype=bool)
    if beyond <= 0 or not np.any((number >= 0) & (lid >= 0)):
        return refused
    order, starts, stops = line_runs(lid, np.flatnonzero(lid >= 0))
    for a, b in zip(starts, stops, strict=True):
        seq = order[a:b]
        kept = number[seq] >= 0
        if np.count_nonzero(kept) < _JUDGED + _INNER_LEAST:
            continue
        # each numbered run's ends with an unnumbered peak of the line next beyond them
        change = np.flatnonzero(kept[1:] != kept[:-1])  # between change and change + 1
        ends = [(int(k) + 1, 1) if kept[k + 1] else (int(k), -1) for k in change]
        for e, inward in ends:
            far = _walk(kept, e - inward, -inward, want=False, most=_BEYOND_MOST)
            inner = _walk(kept, e, inward, want=True, most=_JUDGED + _INNER_MOST)
            if far.size < _BEYOND_LEAST or inner.size < _JUDGED + _INNER_LEAST:
                continue
            # each course fitted once per end, read at the judged peaks' columns
            far_course = _course(seq[far], col, row)
            own_course = _course(seq[inner[_JUDGED:]], col, row)
            for p in seq[inner[:_JUDGED]]:
                on_far = abs(row[p] - np.polyval(far_course, col[p]))
                off_own = abs(row[p] - np.polyval(own_course, col[p]))
                # from the outermost peak in: the surface changes once
                if on_far >= beyond or off_own < departure:
                    break
                refused[p] = True
    return refused


def _walk(kept: np.ndarray, start: int, step: int, *, want: bool, most: int) -> np.ndarray:
    """Positions from ``start`` on by ``step`` while ``kept`` is ``want``, at most ``most``."""
    pos: list[int] = []
    k = start
    while 0 <= k < kept.size and bool(kept[k]) == want and len(pos) < most:
        pos.append(k)
        k += step
    return np.asarray(pos, dtype=np.int64)
