"""Short numbered lines that no column confirms from both sides, and small inherited
components touched from one side only: refused."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from rasterserver_plugins.numbering_params import CodeWindowParams
from rasterserver_plugins.one_sided_lines import one_sided_components, one_sided_lines


def _frame(pieces: list[tuple[int, range, float, bool]]) -> tuple[np.ndarray, ...]:
    """Peaks of ``(line, columns, row, numbered)`` pieces sorted by ``(col, row)``; a line's
    number is 100 + its id. Returns col, line_id, number."""
    col, row, lid, num = [], [], [], []
    for line, columns, r, numbered in pieces:
        for c in columns:
            col.append(c)
            row.append(r)
            lid.append(line)
            num.append(100 + line if numbered else -1)
    order = np.lexsort((np.array(row), np.array(col)))
    return (
        np.array(col, dtype=np.int32)[order],
        np.array(lid, dtype=np.int32)[order],
        np.array(num, dtype=np.int32)[order],
    )


def test_a_short_line_numbered_below_its_one_neighbour_is_refused() -> None:
    """Lines 0-2 of a back over 40 columns; line 3, four peaks below line 2 (an arm's or a
    cloth's piece), has a numbered peak above it and an unnumbered one below."""
    col, lid, num = _frame(
        [(0, range(40), 0.0, True), (1, range(40), 10.0, True), (2, range(40), 20.0, True),
         (3, range(30, 34), 30.0, True), (4, range(28, 36), 40.0, False)]
    )  # fmt: skip
    refused = one_sided_lines(col, lid, num)
    assert np.array_equal(refused, lid == 3)


def test_a_short_line_between_two_numbered_lines_in_one_column_is_kept() -> None:
    col, lid, num = _frame(
        [(0, range(40), 0.0, True), (3, range(30, 34), 10.0, True), (4, range(33, 40), 20.0, True)]
    )
    refused = one_sided_lines(col, lid, num, max_peaks=7)
    # line 3 lies between 0 and 4 in column 33; line 4 (7 peaks) lies between 3 and nothing
    # in 33 and below 0 only in 34-39: refused
    assert not np.any(refused[lid == 3])
    assert np.all(refused[lid == 4])
    assert not np.any(refused[lid == 0])


def test_long_lines_and_the_backs_top_and_bottom_lines_are_kept() -> None:
    col, lid, num = _frame([(0, range(40), 0.0, True), (1, range(40), 10.0, True)])
    assert not np.any(one_sided_lines(col, lid, num))
    # a line of exactly max_peaks numbered peaks is judged, one more is not
    col, lid, num = _frame([(0, range(40), 0.0, True), (1, range(10, 17), 10.0, True)])
    assert np.array_equal(one_sided_lines(col, lid, num, max_peaks=7), lid == 1)
    assert not np.any(one_sided_lines(col, lid, num, max_peaks=6))
    assert not np.any(one_sided_lines(col, lid, num, max_peaks=0))


def test_only_numbered_peaks_count_and_peaks_in_no_line_are_left_alone() -> None:
    """Line 1 has 20 peaks of which 5 numbered: a short numbered line. A numbered peak in no
    line (line id -1) is not judged."""
    col, lid, num = _frame([(0, range(40), 0.0, True), (1, range(20), 10.0, True)])
    num = num.copy()
    num[(lid == 1) & (col >= 5)] = -1
    refused = one_sided_lines(col, lid, num)
    assert np.array_equal(refused, (lid == 1) & (col < 5))
    lid = lid.copy()
    lid[(lid == 1) & (col < 5)] = -1
    assert not np.any(one_sided_lines(col, lid, num))


@pytest.mark.parametrize("n", [0, 1])
def test_degenerate_inputs(n: int) -> None:
    col = np.zeros(n, dtype=np.int32)
    lid = np.zeros(n, dtype=np.int32)
    got = one_sided_lines(col, lid, np.full(n, -1, dtype=np.int32))
    assert got.shape == (n,) and not np.any(got)
    if n:  # one numbered peak alone: a line of one peak, one-sided
        assert one_sided_lines(col, lid, np.array([100], dtype=np.int32)).tolist() == [True]


def test_the_parameter_is_validated() -> None:
    assert CodeWindowParams().one_sided_peaks == 6  # version 29; 5 in versions 21-28
    assert CodeWindowParams(one_sided_peaks=0).one_sided_peaks == 0
    with pytest.raises(ValidationError):
        CodeWindowParams(one_sided_peaks=-1)


def test_an_inherited_component_touched_from_above_only_is_refused() -> None:
    """Lines 0-2 (component 0) of a back; lines 3 and 4 (component 1, inherited) below line
    2 over columns 10-19, with an unnumbered cloth line below them: touched from above
    only, as a cloth's lines below a waistband. Inherited from above and below (component
    2 between lines 0 and 1's ends, and line 5 below it), it stays."""
    col, lid, num = _frame(
        [(0, range(40), 0.0, True), (1, range(40), 10.0, True), (2, range(40), 20.0, True),
         (3, range(10, 20), 30.0, True), (4, range(10, 20), 40.0, True),
         (6, range(8, 22), 50.0, False)]
    )  # fmt: skip
    comps = np.array([0, 0, 0, 1, 1, 9, 9], dtype=np.int32)
    linked = np.zeros(10, dtype=bool)
    linked[1] = True
    refused = one_sided_components(col, lid, num, comps, linked)
    assert np.array_equal(refused, np.isin(lid, [3, 4]))
    # a component the code placed (not linked) is not judged
    assert not np.any(one_sided_components(col, lid, num, comps, np.zeros(10, dtype=bool)))
    # larger than max_peaks (20 numbered peaks): kept
    assert not np.any(one_sided_components(col, lid, num, comps, linked, max_peaks=19))
    assert np.any(one_sided_components(col, lid, num, comps, linked, max_peaks=20))
    assert not np.any(one_sided_components(col, lid, num, comps, linked, max_peaks=0))
    # numbered line 5 below line 4 in one column (another component): touched from both
    col, lid, num = _frame(
        [(0, range(40), 0.0, True), (1, range(40), 10.0, True), (2, range(40), 20.0, True),
         (3, range(10, 20), 30.0, True), (4, range(10, 20), 40.0, True),
         (5, range(19, 30), 50.0, True)]
    )  # fmt: skip
    comps = np.array([0, 0, 0, 1, 1, 0], dtype=np.int32)
    assert not np.any(one_sided_components(col, lid, num, comps, linked[:2]))


def test_an_inherited_component_touching_nothing_numbered_is_refused() -> None:
    # its contacts were refused since: nothing numbered confirms its count on either side
    col, lid, num = _frame([(0, range(40), 0.0, False), (1, range(10, 20), 10.0, True)])
    comps = np.array([0, 1], dtype=np.int32)
    refused = one_sided_components(col, lid, num, comps, np.array([False, True]))
    assert np.array_equal(refused, lid == 1)


@pytest.mark.parametrize("n", [0, 1])
def test_components_of_degenerate_inputs(n: int) -> None:
    col = np.zeros(n, dtype=np.int32)
    lid = np.full(n, -1, dtype=np.int32)
    num = np.full(n, 100, dtype=np.int32)
    comps = np.zeros(0, dtype=np.int32)
    got = one_sided_components(col, lid, num, comps, np.zeros(0, dtype=bool))
    assert got.shape == (n,) and not np.any(got)
    if n:  # a numbered peak of no line is never judged
        got = one_sided_components(col, lid, num, np.array([0]), np.array([True]))
        assert not np.any(got)
    assert CodeWindowParams().linked_one_sided == 50
    with pytest.raises(ValidationError):
        CodeWindowParams(linked_one_sided=-1)
