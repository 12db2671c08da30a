"""Consecutive numbers a skipped line apart in their column: refused, and their lines."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.skipped_lines import skipped_line_gaps, skipped_lines

SPACING = 6.0


def _peaks(
    lines: list[tuple[int, int, int, float, int]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Peaks of horizontal lines ``(line_id, first_col, last_col, row, number)`` (-1:
    unnumbered), sorted by ``(col, row)``."""
    col, row, lid, num = [], [], [], []
    for line, c0, c1, r, n in lines:
        cols = np.arange(c0, c1 + 1)
        col.append(cols)
        row.append(np.full(cols.size, r))
        lid.append(np.full(cols.size, line))
        num.append(np.full(cols.size, n))
    c, r, l_, n = (np.concatenate(a) for a in (col, row, lid, num))
    order = np.lexsort((r, c))
    return c[order], r[order], l_[order].astype(np.int32), n[order].astype(np.int32)


def _back_over_dark_cloth() -> tuple[np.ndarray, ...]:
    """Back lines 110-118 one spacing apart over columns 0-199; below them, over columns
    100-199, the waistband's line 119 (unnumbered) and a dark cloth that shows only the
    heavy lines 121, 123 and 125 (the light lines between went unfound), numbered 120, 121
    and 122 as if neighbours."""
    back = [(k, 0, 199, SPACING * k, k) for k in range(110, 119)]
    band = [(119, 100, 199, SPACING * 119, -1)]
    cloth = [(200 + j, 100, 199, SPACING * (121 + 2 * j), 120 + j) for j in range(3)]
    return _peaks(back + band + cloth)


def test_consecutive_numbers_two_spacings_apart_are_refused_with_their_lines() -> None:
    col, row, lid, number = _back_over_dark_cloth()
    gaps = skipped_line_gaps(col, row, number)
    # the cloth's pairs (120-121, 121-122) lie two spacings apart, the back's one above
    assert set(lid[gaps].tolist()) == {200, 201, 202}
    refused = skipped_lines(col, row, lid, number)
    assert set(lid[refused].tolist()) == {200, 201, 202}
    assert np.all(refused[lid >= 200])  # the cloth's lines whole
    assert not np.any(refused[lid < 200])  # the back stays


def test_a_line_with_few_refused_peaks_keeps_the_rest() -> None:
    """A piece of three peaks (columns 197-199) two spacings below the last back line,
    numbered as its neighbour: the pairs are refused; the back line, three of whose 200
    peaks are in them, keeps its other columns unless the share is 0."""
    back = [(k, 0, 199, SPACING * k, k) for k in range(110, 119)]
    piece = [(300, 197, 199, SPACING * 120, 119)]
    col, row, lid, number = _peaks(back + piece)
    pairs = skipped_line_gaps(col, row, number)
    assert set(col[pairs].tolist()) == {197, 198, 199}
    assert set(lid[pairs].tolist()) == {118, 300}
    kept = skipped_lines(col, row, lid, number, min_peaks=3, line_share=0.2)
    assert np.array_equal(kept, pairs)
    whole = skipped_lines(col, row, lid, number, min_peaks=3, line_share=0.0)
    assert np.array_equal(whole, np.isin(lid, [118, 300]))
    assert np.array_equal(skipped_lines(col, row, lid, number, min_peaks=0), pairs)


def test_a_gently_widening_column_and_a_lone_pair_are_kept() -> None:
    # lines spreading by 4 % a line (a surface turning from the projector): no skip
    rows = SPACING * np.cumsum(1.04 ** np.arange(12))
    col, row, lid, number = _peaks([(k, 0, 49, float(rows[k]), 100 + k) for k in range(12)])
    assert not np.any(skipped_lines(col, row, lid, number))
    # a pair two spacings apart with no single gap beside it in its column: not judged
    col, row, lid, number = _peaks([(0, 0, 49, 0.0, 5), (1, 0, 49, 2 * SPACING, 6)])
    assert not np.any(skipped_lines(col, row, lid, number))


@pytest.mark.parametrize("ratio", [1.5, 1.9, 2.5])
def test_the_ratio_decides(ratio: float) -> None:
    """Back lines one spacing apart, then a pair numbered consecutively 2.2 spacings apart."""
    lines = [(k, 0, 29, SPACING * k, k) for k in range(10)]
    lines += [(10, 0, 29, SPACING * 9 + 2.2 * SPACING, 10)]
    col, row, lid, number = _peaks(lines)
    refused = skipped_lines(col, row, lid, number, ratio=ratio)
    assert np.any(refused) == (ratio <= 2.2)
    if np.any(refused):
        assert set(lid[refused].tolist()) == {9, 10}  # both: the column cannot tell which


def test_degenerate_inputs() -> None:
    empty = np.zeros(0)
    assert skipped_lines(empty, empty, empty.astype(np.int32), empty.astype(np.int32)).size == 0
    col, row, lid, number = _back_over_dark_cloth()
    nothing = np.full(number.size, -1, dtype=np.int32)
    assert not np.any(skipped_lines(col, row, lid, nothing))
    assert not np.any(skipped_line_gaps(col, row, number, side=0))
    # peaks with no line: refused as pairs, never as lines
    free = np.full(lid.size, -1, dtype=np.int32)
    refused = skipped_lines(col, row, free, number)
    assert np.array_equal(refused, skipped_line_gaps(col, row, number))
