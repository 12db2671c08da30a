"""Small numbered pieces that no standing contact joins to the frame's main block: refused."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from rasterserver_plugins.detached_pieces import detached_pieces, numbered_blocks
from rasterserver_plugins.numbering_params import CodeWindowParams
from rasterserver_plugins.skipped_lines import consecutive_pairs

from rasterserver.raster import default_raster

SPACING = 6.0
RASTER = default_raster()


def _width(number: int) -> float:
    return float(RASTER.widths[RASTER.index_of(number)])


def _peaks(
    lines: list[tuple[int, int, int, float, int, float]],
) -> tuple[np.ndarray, ...]:
    """Peaks of horizontal lines ``(line_id, first_col, last_col, row, number, dimming)``,
    their true numbers giving the areas (the line's width over ``dimming``); numbers -1
    for unnumbered; sorted by ``(col, row)``. Every line's true number is its row over
    the spacing."""
    col, row, lid, num, area = [], [], [], [], []
    for line, c0, c1, r, n, dim in lines:
        cols = np.arange(c0, c1 + 1)
        col.append(cols)
        row.append(np.full(cols.size, r))
        lid.append(np.full(cols.size, line))
        num.append(np.full(cols.size, n))
        area.append(np.full(cols.size, 10.0 * _width(round(r / SPACING)) / dim))
    c, r, l_, n, a = (np.concatenate(x) for x in (col, row, lid, num, area))
    order = np.lexsort((r, c))
    return c[order], r[order], l_[order].astype(np.int32), n[order].astype(np.int32), a[order]


BACK = [(k, 0, 199, SPACING * k, k, 1.0) for k in range(40, 52)]


def test_a_piece_below_a_brightness_step_is_refused_and_the_back_kept() -> None:
    """Under the back's last line (51), a dark cloth 1.4 spacings lower over columns
    100-119: its three lines, five times dimmer, are numbered 52-54 (one off) and touch the
    back at column neighbours whose brightness departs from the code's."""
    cloth = [(100 + j, 100, 119, SPACING * (52.4 + j), 52 + j, 5.0) for j in range(3)]
    col, row, lid, number, area = _peaks(BACK + cloth)
    refused = detached_pieces(col, row, lid, number, area, RASTER)
    assert np.array_equal(refused, lid >= 100)
    labels = numbered_blocks(col, row, lid, number, area, RASTER)
    assert np.unique(labels[lid < 100]).size == 1  # the back is one block


def test_a_piece_held_by_a_regular_contact_is_kept() -> None:
    """The same piece as bright as the back, one spacing below it: joined, kept."""
    cloth = [(100 + j, 100, 119, SPACING * (52 + j), 52 + j, 1.0) for j in range(3)]
    col, row, lid, number, area = _peaks(BACK + cloth)
    assert not np.any(detached_pieces(col, row, lid, number, area, RASTER))
    assert np.unique(numbered_blocks(col, row, lid, number, area, RASTER)).size == 1


def test_a_piece_beyond_refused_peaks_is_refused_unless_large() -> None:
    """A block of short lines beyond an unnumbered line (its peaks refused by the checks):
    refused when it has at most ``max_peaks`` peaks."""
    gap_line = [(90, 100, 119, SPACING * 52, -1, 1.0)]
    piece = [(100 + j, 100, 119, SPACING * (53 + j), 53 + j, 1.0) for j in range(3)]
    col, row, lid, number, area = _peaks(BACK + gap_line + piece)
    refused = detached_pieces(col, row, lid, number, area, RASTER, max_peaks=60)
    assert np.array_equal(refused, lid >= 100)
    assert not np.any(detached_pieces(col, row, lid, number, area, RASTER, max_peaks=59))
    assert not np.any(detached_pieces(col, row, lid, number, area, RASTER, max_peaks=0))


@pytest.mark.parametrize("high", [1.3, 1.5])
def test_the_gap_range_decides(high: float) -> None:
    """A piece 1.4 spacings below the back and as bright: joined only when 1.4 lies within
    the range."""
    cloth = [(100 + j, 100, 119, SPACING * (52.4 + j), 52 + j, 1.0) for j in range(3)]
    col, row, lid, number, area = _peaks(BACK + cloth)
    refused = detached_pieces(col, row, lid, number, area, RASTER, gap_high=high)
    assert np.any(refused) == (high < 1.4)


def test_a_line_with_a_gap_of_more_columns_than_col_gap_splits() -> None:
    """Two pieces of one line with a gap of four columns: two blocks unless col_gap allows."""
    col, row, lid, number, area = _peaks([(1, 0, 9, 60.0, 10, 1.0), (1, 14, 29, 60.0, 10, 1.0)])
    assert np.unique(numbered_blocks(col, row, lid, number, area, RASTER)).size == 2
    labels = numbered_blocks(col, row, lid, number, area, RASTER, col_gap=5)
    assert np.unique(labels).size == 1
    refused = detached_pieces(col, row, lid, number, area, RASTER)
    assert np.array_equal(refused, col < 10)  # the smaller piece


def test_degenerate_inputs() -> None:
    empty = np.zeros(0)
    assert detached_pieces(empty, empty, empty.astype(np.int32), empty.astype(np.int32),
                           empty, RASTER).shape == (0,)  # fmt: skip
    col, row, lid, number, area = _peaks(BACK)
    none = np.full(number.shape, -1, dtype=np.int32)
    assert not np.any(detached_pieces(col, row, lid, none, area, RASTER))
    assert np.all(numbered_blocks(col, row, lid, none, area, RASTER) == -1)
    # one block only: the largest is kept whatever its size
    assert not np.any(detached_pieces(col[:30], row[:30], lid[:30], number[:30], area[:30],
                                      RASTER))  # fmt: skip


def test_a_zero_area_joins_nothing_and_an_empty_gap_range_is_refused() -> None:
    col, row, lid, number, area = _peaks(BACK)
    area[col == 5] = 0.0  # column 5's pairs cannot be judged by their brightness
    labels = numbered_blocks(col, row, lid, number, area, RASTER)
    assert np.unique(labels).size == 1  # the lines still join column 5 to the rest
    with pytest.raises(ValidationError, match="detached_gap_low"):
        CodeWindowParams(detached_gap_low=1.6, detached_gap_high=1.2)


def test_consecutive_pairs_report_the_gaps_beside_them() -> None:
    col, row, _, number, _ = _peaks(BACK)
    a, b, gap, median = consecutive_pairs(col, row, number)
    assert a.size == 200 * 11 and np.all(number[b] - number[a] == 1)
    assert np.allclose(gap, SPACING) and np.allclose(median, SPACING)
    # too few gaps beside a pair: inf
    a, b, gap, median = consecutive_pairs(col[:2], row[:2], number[:2])
    assert a.size == 1 and np.isinf(median[0])
