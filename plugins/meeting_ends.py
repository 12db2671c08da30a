"""A line's end peak that continues, as well, another numbered line ending beside it.

Where an arm's edge or a cloth's edge cuts the raster, the lines of one surface end and
the next surface's lines start in the next column at nearly the same rows, one or two
numbers off. The peak at the meeting point belongs to one of the two lines, and the
line search linked it to one of them; where it lies on the straight course of the other
line (within ``meet_tolerance`` rows of the course of that line's first peaks) and that
line carries another number, the image does not decide which surface it lies on, and it
is refused: a wrong number is worse than none.

On the clinic tuning frames rendered for version 26 (65800-66999, an Intel Xeon) two of
the five wrongly numbered single peaks were such meetings: an arm's peak at the end of a
trunk line where the trunk's line turns away (66005, ``mseq7``) and a trunk peak at the
start of an arm's line (66703, ``w9-45to55``). The rule refuses 83 right peaks of the
back over those 1,200 scenes (0.0004 point of its coverage); where the other line is
unnumbered it would cost 25 times as much, and an unnumbered line contradicts nothing.
On fresh held-out frames (clinic rasters 67400-68599, the held-out raster 68600-68999;
criteria written before) it caught none of the 17 wrongly numbered peaks, so it stayed an
option of the stage (``meet_tolerance``), off (BENCHMARKS.md "Real bodies", 2026-12-01
(39)). With peaks version 6 it took two arm meetings on the tuning frames of section (44),
and with :mod:`.outer_ends` and one-sided lines of six peaks it was judged on fresh frames
again and adopted as a step of numbering version 29 (1.0).
"""

from __future__ import annotations

import numpy as np

from .numbering_checks import line_runs, numbered_peaks

__all__ = ["meeting_ends"]


def _course(col: np.ndarray, row: np.ndarray, at: int) -> float:
    """The row at column ``at`` of the straight line through the peaks (one: its row)."""
    if col.size == 1 or np.ptp(col) == 0:
        return float(row.mean())
    slope, icept = np.polyfit(col.astype(np.float64), row.astype(np.float64), 1)
    return float(slope * at + icept)


def meeting_ends(
    col: np.ndarray,
    row: np.ndarray,
    line_id: np.ndarray,
    number: np.ndarray,
    *,
    tolerance: float = 1.0,
    least_peaks: int = 4,
    course_peaks: int = 3,
) -> np.ndarray:
    """The end peaks of numbered lines that lie on the course of another numbered line
    ending in the next column beyond them with another number.

    Parameters
    ----------
    col, row : numpy.ndarray
        Peaks sorted by ``(col, row)``.
    line_id : numpy.ndarray
        Line of every peak, -1 for none.
    number : numpy.ndarray
        Per-peak absolute number, -1 when unnumbered.
    tolerance : float
        Largest distance (rows) of the end peak from the other line's course; 0 judges
        none.
    least_peaks : int
        Fewest numbered peaks of a line whose ends are judged.
    course_peaks : int
        Peaks at the other line's end whose straight course is continued.

    Returns
    -------
    numpy.ndarray
        ``(N,)`` bool, True for the refused peaks.
    """
    col, row, lid, number = numbered_peaks(col, row, line_id, number)
    refused = np.zeros(number.size, dtype=bool)
    if tolerance <= 0 or not np.any((number >= 0) & (lid >= 0)):
        return refused
    order, starts, stops = line_runs(lid, np.flatnonzero(lid >= 0))
    # every line's own ends (all its peaks, numbered or not), and its numbers
    first_at: dict[int, list[int]] = {}
    last_at: dict[int, list[int]] = {}
    numbers: dict[int, np.ndarray] = {}
    for k, (a, b) in enumerate(zip(starts, stops, strict=True)):
        first_at.setdefault(int(col[order[a]]), []).append(k)
        last_at.setdefault(int(col[order[b - 1]]), []).append(k)
        own = number[order[a:b]]
        numbers[k] = np.unique(own[own >= 0])
    for k, (a, b) in enumerate(zip(starts, stops, strict=True)):
        seq = order[a:b]
        kept = seq[number[seq] >= 0]
        if kept.size < max(least_peaks, 1):
            continue
        for end, step in ((kept[0], -1), (kept[-1], 1)):
            c = int(col[end])
            # lines whose far end lies in the next column beyond, running away from this one
            others = first_at.get(c + 1, []) if step == 1 else last_at.get(c - 1, [])
            for o in others:
                # an unnumbered line contradicts nothing; one carrying this number may be
                # this line's own continuation
                if o == k or numbers[o].size == 0 or np.any(numbers[o] == number[end]):
                    continue
                seq_o = order[starts[o] : stops[o]]
                near = seq_o[:course_peaks] if step == 1 else seq_o[-course_peaks:]
                if abs(row[end] - _course(col[near], row[near], c)) < tolerance:
                    refused[end] = True
                    break
    return refused
