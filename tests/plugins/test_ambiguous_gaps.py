"""Short lines numbered across a gap between two counts of line spacings: refused."""

from __future__ import annotations

import numpy as np


def _columns(
    rows: list[float], numbers: list[int], lines: list[int], n_cols: int
) -> tuple[np.ndarray, ...]:
    """The same column ``n_cols`` times side by side, sorted by (col, row)."""
    k = len(rows)
    return (
        np.repeat(np.arange(n_cols), k),
        np.tile(np.asarray(rows, dtype=np.float64), n_cols),
        np.tile(np.asarray(lines, dtype=np.int64), n_cols),
        np.tile(np.asarray(numbers, dtype=np.int32), n_cols),
    )


def test_gap_departures_measure_the_gap_against_the_single_gap_beyond() -> None:
    from rasterserver_plugins.ambiguous_gaps import gap_departures

    # lines 127, 128, 129 6.4 px apart, then a cloth line 9.5 px below 129 numbered 130
    col, row, _, number = _columns([762.6, 768.8, 775.2, 784.7], [127, 128, 129, 130], [0] * 4, 1)
    dep = gap_departures(col, row, number)
    # the top line: nothing above it, judged from below (6.2 px against the 6.4 beyond)
    assert abs(dep[0] - (6.2 / 6.4 - 1) * -1) < 1e-9
    assert abs(dep[3] - (9.5 / 6.4 - 1)) < 1e-9
    # two numbers apart across 2.5 spacings departs as much
    col, row, _, number = _columns([100.0, 106.0, 121.0], [10, 11, 13], [0] * 3, 1)
    assert abs(gap_departures(col, row, number)[2] - 0.5) < 1e-9
    # whole counts depart by nothing; unnumbered and out-of-order neighbours are not used
    col, row, _, number = _columns([100.0, 106.0, 112.0, 124.0], [10, 11, 12, 14], [0] * 4, 1)
    assert np.allclose(gap_departures(col, row, number)[2:], 0.0)
    col, row, _, number = _columns([100.0, 106.0, 115.0], [10, -1, 12], [0] * 3, 1)
    assert np.isnan(gap_departures(col, row, number)).all()
    col, row, _, number = _columns([100.0, 106.0, 115.0], [12, 11, 10], [0] * 3, 1)
    assert np.isnan(gap_departures(col, row, number)).all()


def test_a_short_line_across_an_ambiguous_gap_is_refused_and_a_long_one_kept() -> None:
    from rasterserver_plugins.ambiguous_gaps import ambiguous_gap_lines

    # nine columns: skin lines 0-2 (127-129), a cloth line 3 numbered 130 at 1.5 spacings
    col, row, line, number = _columns([762.6, 768.8, 775.2, 784.7], [127, 128, 129, 130],
                                      [0, 1, 2, 3], 9)  # fmt: skip
    refused = ambiguous_gap_lines(col, row, line, number, max_peaks=20, departure=0.4)
    assert refused.tolist() == (line == 3).tolist()
    # the same line over 21 columns is long: its number is read along it
    col, row, line, number = _columns([762.6, 768.8, 775.2, 784.7], [127, 128, 129, 130],
                                      [0, 1, 2, 3], 21)  # fmt: skip
    assert not ambiguous_gap_lines(col, row, line, number, max_peaks=20).any()
    # a gap of 1.3 spacings departs 0.3: kept at 0.4, refused at 0.25
    col, row, line, number = _columns([100.0, 106.0, 112.0, 119.8], [10, 11, 12, 13],
                                      [0, 1, 2, 3], 5)  # fmt: skip
    assert not ambiguous_gap_lines(col, row, line, number, departure=0.4).any()
    assert ambiguous_gap_lines(col, row, line, number, departure=0.25).sum() == 5
    # off, and degenerate inputs
    assert not ambiguous_gap_lines(col, row, line, number, max_peaks=0, departure=0.25).any()
    none = np.full(number.size, -1, np.int32)
    assert not ambiguous_gap_lines(col, row, line, none).any()
    empty = np.zeros(0, np.int64)
    assert ambiguous_gap_lines(empty, empty * 1.0, empty, empty).size == 0


def test_the_median_decides_over_a_line_with_some_ambiguous_columns() -> None:
    from rasterserver_plugins.ambiguous_gaps import ambiguous_gap_lines

    # line 3 over 6 columns: 1.5 spacings below in 2, a whole spacing in 4 -> median 0
    parts = [_columns([100.0, 106.0, 112.0, r], [10, 11, 12, 13], [0, 1, 2, 3], 1)
             for r in (121.0, 121.0, 118.0, 118.0, 118.0, 118.0)]  # fmt: skip
    col = np.concatenate([p[0] + i for i, p in enumerate(parts)])
    row, line, number = (np.concatenate([p[j] for p in parts]) for j in (1, 2, 3))
    assert not ambiguous_gap_lines(col, row, line, number).any()
    # peaks on no line (-1) are never judged, however far off their gaps lie
    row = np.where(line == 3, 121.0, row)
    assert ambiguous_gap_lines(col, row, line, number).sum() == 6
    line = np.where(line == 3, -1, line)
    assert not ambiguous_gap_lines(col, row, line, number).any()
