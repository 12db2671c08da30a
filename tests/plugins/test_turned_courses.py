"""A line's numbered end peaks lying on the course of its refused peaks beyond them, off
its own course: refused (the line turns there onto another surface)."""

from __future__ import annotations

import numpy as np
from line_pieces import line_pieces
from rasterserver_plugins.turned_courses import turned_courses


def _refused_columns(pieces: list[tuple[int, range, float, float, int]], **kw: float) -> list[int]:
    col, row, lid, num = line_pieces(pieces)
    return sorted(col[turned_courses(col, row, lid, num, **kw)].tolist())


def test_end_peaks_on_the_refused_surface_s_course_are_refused_from_the_outside_in() -> None:
    """A trunk line (slope 1) turns at column 20 onto an arm (flat, 67624): its numbered
    peaks at columns 20-21 follow the arm's course, as its refused peaks 22-26 do, and are
    refused; the trunk's peaks keep their number. The same at a line's start."""
    trunk, arm = (0, range(20), 50.0, 1.0, 61), (0, range(20, 22), 68.0, 0.0, 61)
    beyond = (0, range(22, 27), 68.0, 0.0, -1)
    assert _refused_columns([trunk, arm, beyond]) == [20, 21]
    # mirrored: the refused arm first, the trunk line after the turn
    start = [(0, range(0, 5), 68.0, 0.0, -1), (0, range(5, 7), 68.0, 0.0, 61)]
    assert _refused_columns([*start, (0, range(7, 30), 65.0, 1.0, 61)]) == [5, 6]


def test_three_peaks_at_most_and_only_while_each_lies_on_the_other_course() -> None:
    """Four numbered peaks on the arm's course: the outermost three are refused; where the
    second peak in lies on the line's own course, only the outermost is."""
    trunk, beyond = (0, range(20), 50.0, 1.0, 61), (0, range(24, 29), 68.0, 0.0, -1)
    assert _refused_columns([trunk, (0, range(20, 24), 68.0, 0.0, 61), beyond]) == [21, 22, 23]
    own = (0, range(20), 50.0, 1.0, 61)
    assert _refused_columns(
        [
            own,
            (0, range(20, 22), 69.5, 0.0, 61),
            (0, range(22, 23), 68.0, 0.0, 61),
            (0, range(23, 28), 68.0, 0.0, -1),
        ]
    ) == [22]


def test_ends_the_course_does_not_decide_keep_their_numbers() -> None:
    """Nothing is refused where the line runs straight on into its refused peaks (they
    were refused for another reason), where fewer than three refused peaks lie beyond or
    fewer than seven numbered peaks within, where the end is off both courses, with the
    rule off, or on an empty frame."""
    straight = [(0, range(30), 50.0, 1.0, 61), (0, range(30, 35), 50.0, 1.0, -1)]
    assert _refused_columns(straight) == []
    trunk, arm = (0, range(20), 50.0, 1.0, 61), (0, range(20, 22), 68.0, 0.0, 61)
    assert _refused_columns([trunk, arm, (0, range(22, 24), 68.0, 0.0, -1)]) == []
    short = [(0, range(16, 20), 50.0, 1.0, 61), arm, (0, range(22, 27), 68.0, 0.0, -1)]
    assert _refused_columns(short) == []
    off_both = [trunk, (0, range(20, 22), 66.0, 0.0, 61), (0, range(22, 27), 68.0, 0.0, -1)]
    assert _refused_columns(off_both) == []
    assert _refused_columns([trunk, arm, (0, range(22, 27), 68.0, 0.0, -1)], beyond=0.0) == []
    empty = np.zeros(0, np.int32)
    assert turned_courses(empty, np.zeros(0), empty, empty).size == 0
