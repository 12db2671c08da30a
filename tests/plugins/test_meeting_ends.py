"""A line's end peak lying as well on the course of another numbered line that ends beside
it with another number: refused (where two surfaces' lines meet)."""

from __future__ import annotations

import numpy as np
from line_pieces import line_pieces as _frame
from rasterserver_plugins.meeting_ends import meeting_ends


def _at(col: np.ndarray, lid: np.ndarray, line: int, column: int) -> list[int]:
    return np.flatnonzero((lid == line) & (col == column)).tolist()


def test_the_peaks_where_two_lines_of_other_numbers_meet_are_refused() -> None:
    """A trunk line numbered 84 ends at column 19; an arm's line numbered 83 starts at
    column 20 on the trunk line's course (66005): the image does not tell which surface
    either peak at the meeting lies on, so both are refused, and nothing else."""
    col, row, lid, num = _frame([(0, range(20), 50.0, 0.5, 84), (1, range(20, 40), 60.2, 0.0, 83)])
    refused = meeting_ends(col, row, lid, num, tolerance=1.0)
    assert np.flatnonzero(refused).tolist() == sorted(_at(col, lid, 0, 19) + _at(col, lid, 1, 20))


def test_lines_that_do_not_contradict_each_other_or_do_not_meet_keep_their_ends() -> None:
    """Nothing is refused where the other line is unnumbered (it contradicts nothing),
    carries the same number (the line's own continuation, cut by the line search), runs
    past the end peak by more than the tolerance, or ends two columns beyond; nor with the
    rule off or on an empty frame."""
    cases = [
        [(0, range(20), 50.0, 0.5, 84), (1, range(20, 40), 60.2, 0.0, -1)],
        [(0, range(20), 50.0, 0.5, 84), (1, range(20, 40), 60.2, 0.0, 84)],
        [(0, range(20), 50.0, 0.5, 84), (1, range(20, 40), 61.5, 0.0, 83)],
        [(0, range(20), 50.0, 0.5, 84), (1, range(21, 40), 60.2, 0.0, 83)],
    ]
    for lines in cases:
        col, row, lid, num = _frame(lines)
        assert not np.any(meeting_ends(col, row, lid, num, tolerance=1.0))
    col, row, lid, num = _frame([(0, range(20), 50.0, 0.5, 84), (1, range(20, 40), 60.2, 0.0, 83)])
    assert not np.any(meeting_ends(col, row, lid, num, tolerance=0.0))
    empty = np.zeros(0, np.int32)
    assert meeting_ends(empty, np.zeros(0), empty, empty).size == 0


def test_only_lines_of_four_numbered_peaks_or_more_are_judged() -> None:
    """A line of three numbered peaks keeps its end (other steps judge short lines), yet
    the long line it meets loses its end peak to it; unnumbered peaks and peaks of no
    line count for no line."""
    col, row, lid, num = _frame([(0, range(20), 50.0, 0.5, 84), (1, range(20, 23), 60.2, 0.0, 83)])
    refused = meeting_ends(col, row, lid, num, tolerance=1.0)
    assert np.flatnonzero(refused).tolist() == _at(col, lid, 0, 19)
    lid[lid == 1] = -1
    assert not np.any(meeting_ends(col, row, lid, num, tolerance=1.0))
