"""Peaks bracketed in their column by numbered ones: numbered by counting the spacings."""

from __future__ import annotations

import numpy as np


def _column(rows: list[float], numbers: list[int], col: int = 0) -> tuple[np.ndarray, ...]:
    return (
        np.full(len(rows), col, np.int64),
        np.asarray(rows, dtype=np.float64),
        np.asarray(numbers, dtype=np.int32),
    )


def _fill(
    col: np.ndarray, row: np.ndarray, number: np.ndarray, max_run: int = 8, tolerance: float = 0.2
) -> np.ndarray:
    from rasterserver_plugins.bracketed_peaks import bracketed_numbers

    spacing = np.full(col.size, 10.0)
    return bracketed_numbers(col, row, number, spacing, max_run=max_run, tolerance=tolerance)


def test_a_run_between_numbered_peaks_one_spacing_apart_is_numbered() -> None:
    col, row, number = _column([100.0, 110.5, 119.6, 130.2, 140.0], [10, -1, -1, 13, 14])
    out = _fill(col, row, number)
    assert out.tolist() == [10, 11, 12, 13, 14]
    assert out.dtype == np.int32
    assert number.tolist() == [10, -1, -1, 13, 14]  # the input is left alone


def test_a_gap_that_is_not_one_spacing_leaves_the_run_unnumbered() -> None:
    # a depth step: the count of numbers fits, but one gap is 1.3 spacings, another 0.7
    col, row, number = _column([100.0, 113.0, 120.0], [10, -1, 12])
    assert _fill(col, row, number).tolist() == [10, -1, 12]
    # within the tolerance it is numbered
    col, row, number = _column([100.0, 111.5, 120.0], [10, -1, 12])
    assert _fill(col, row, number).tolist() == [10, 11, 12]
    assert _fill(col, row, number, tolerance=0.1).tolist() == [10, -1, 12]


def test_a_count_that_does_not_add_up_leaves_the_run_unnumbered() -> None:
    # two spacings between numbers three apart: a line hidden somewhere, unknown where
    col, row, number = _column([100.0, 110.0, 120.0], [10, -1, 13])
    assert _fill(col, row, number).tolist() == [10, -1, 13]
    # numbers in the wrong order
    col, row, number = _column([100.0, 110.0, 120.0], [12, -1, 10])
    assert _fill(col, row, number).tolist() == [12, -1, 10]


def test_a_run_longer_than_max_run_is_left() -> None:
    rows = [100.0 + 10.0 * k for k in range(6)]
    col, row, number = _column(rows, [20, -1, -1, -1, -1, 25])
    assert _fill(col, row, number, max_run=3).tolist() == [20, -1, -1, -1, -1, 25]
    assert _fill(col, row, number, max_run=4).tolist() == [20, 21, 22, 23, 24, 25]
    assert _fill(col, row, number, max_run=0).tolist() == [20, -1, -1, -1, -1, 25]


def test_numbered_peaks_of_different_columns_bracket_nothing() -> None:
    from rasterserver_plugins.bracketed_peaks import bracketed_numbers

    # column 0 ends with an unnumbered peak, column 1 starts numbered: sorted by (col, row)
    # they are consecutive, but not one column
    col = np.array([0, 0, 1, 1])
    row = np.array([100.0, 110.0, 120.0, 130.0])
    number = np.array([10, -1, 12, 13], np.int32)
    out = bracketed_numbers(col, row, number, np.full(4, 10.0))
    assert out.tolist() == [10, -1, 12, 13]


def test_unknown_spacing_and_degenerate_inputs() -> None:
    from rasterserver_plugins.bracketed_peaks import bracketed_numbers, fill_brackets

    col, row, number = _column([100.0, 110.0, 120.0], [10, -1, 12])
    assert bracketed_numbers(col, row, number, np.full(3, np.nan)).tolist() == [10, -1, 12]
    empty_i = np.zeros(0, np.int64)
    assert bracketed_numbers(empty_i, empty_i * 1.0, empty_i, empty_i * 1.0).size == 0
    none = np.full(3, -1, np.int32)
    assert bracketed_numbers(col, row, none, np.full(3, 10.0)).tolist() == [-1, -1, -1]
    # no local spacing (no consecutive numbers anywhere): nothing numbered, no note
    out, note = fill_brackets(col, row, number, None, 8, 0.2)
    assert out.tolist() == [10, -1, 12] and note == ""
    out, note = fill_brackets(col, row, np.array([10, -1, 13], np.int32), np.full(3, 10.0), 8, 0.2)
    assert out.tolist() == [10, -1, 13] and note == ""


def test_fill_brackets_with_the_measured_spacing_says_how_many() -> None:
    from rasterserver_plugins.bracketed_peaks import fill_brackets
    from rasterserver_plugins.numbering_checks import local_spacing

    # 30 columns of lines 5..9, 10 px apart; line 7 unnumbered in columns 10-19
    cols = np.repeat(np.arange(30), 5)
    rows = np.tile([10.0, 20.0, 30.0, 40.0, 50.0], 30) + 0.05 * cols
    number = np.tile([5, 6, 7, 8, 9], 30).astype(np.int32)
    gap = (number == 7) & (cols >= 10) & (cols < 20)
    given = np.where(gap, -1, number).astype(np.int32)
    out, note = fill_brackets(cols, rows, given, local_spacing(cols, rows, given), 8, 0.2)
    assert np.array_equal(out, number)
    assert note.startswith("10 unnumbered peak(s) numbered")


def test_a_run_whose_peaks_lines_carry_other_numbers_is_left_unnumbered() -> None:
    from rasterserver_plugins.bracketed_peaks import bracketed_numbers

    # column 0: numbered 55, two unnumbered peaks one spacing apart, numbered 58: the count
    # adds up (56, 57); column 1 holds the same lines numbered elsewhere along them
    col = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    row = np.array([100.0, 110.0, 120.0, 130.0, 100.0, 110.0, 120.0, 130.0])
    number = np.array([55, -1, -1, 58, 55, 56, 57, 58], np.int32)
    spacing = np.full(8, 10.0)
    agreeing = np.array([0, 1, 2, 3, 0, 1, 2, 3])
    # without the lines, and with lines that carry the counted numbers: numbered
    assert bracketed_numbers(col, row, number, spacing)[1:3].tolist() == [56, 57]
    out = bracketed_numbers(col, row, number, spacing, line_id=agreeing)
    assert out[1:3].tolist() == [56, 57]
    # a hidden line and a spurious peak: the peaks' lines carry 57 and 58 further along
    # (212733's arm); the whole run is left, not just the peak that disagrees
    shifted = np.array([0, 2, 3, 3, 0, 1, 2, 3])
    shifted_number = np.array([55, -1, -1, 58, 55, 56, 57, 58], np.int32)
    shifted_number[5:7] = [-1, 57]  # line 1 unnumbered in column 1; line 2 there carries 57
    out = bracketed_numbers(col, row, shifted_number, spacing, line_id=shifted)
    assert out[1:3].tolist() == [-1, -1]
    # lines with no numbered peak, or no line at all (-1): the count decides
    alone = np.array([0, 5, -1, 3, 0, 6, 7, 3])
    out = bracketed_numbers(col, row, np.array([55, -1, -1, 58, 55, -1, -1, 58], np.int32),
                            spacing, line_id=alone)  # fmt: skip
    assert out[1:3].tolist() == [56, 57]


def test_one_disagreeing_peak_leaves_its_run_and_no_other() -> None:
    from rasterserver_plugins.bracketed_peaks import bracketed_numbers

    # two runs in two columns; only the second one's middle peak lies on a line numbered 30
    col = np.array([0, 0, 0, 1, 1, 1, 2])
    row = np.array([100.0, 110.0, 120.0, 100.0, 110.0, 120.0, 110.0])
    number = np.array([10, -1, 12, 10, -1, 12, 30], np.int32)
    line_id = np.array([0, 1, 2, 0, 3, 2, 3])
    out = bracketed_numbers(col, row, number, np.full(7, 10.0), line_id=line_id)
    assert out.tolist() == [10, 11, 12, 10, -1, 12, 30]
    # empty lines array and no lines at all
    none = np.full(7, -1)
    out = bracketed_numbers(col, row, number, np.full(7, 10.0), line_id=none)
    assert out.tolist() == [10, 11, 12, 10, 11, 12, 30]
