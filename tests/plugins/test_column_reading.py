"""Numbered peaks whose column, read on through the unnumbered peaks beyond, places them a
line off: refused."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from rasterserver_plugins.column_reading import log_width_by_number, misread_columns
from rasterserver_plugins.numbering_params import CodeWindowParams

from rasterserver.raster import default_raster

SPACING = 6.0
RASTER = default_raster()
COLUMNS = 10


def _column(
    numbers: list[int], truths: list[int], *, gaps: list[float] | None = None
) -> tuple[np.ndarray, ...]:
    """``COLUMNS`` identical columns of peaks one spacing apart (or ``gaps`` between them),
    numbered ``numbers`` (-1: unnumbered), their areas the code's widths at ``truths``;
    sorted by ``(col, row)``."""
    steps = [SPACING] * (len(numbers) - 1) if gaps is None else gaps
    rows = 100.0 + np.r_[0.0, np.cumsum(steps)]
    area = np.array([10.0 * RASTER.widths[RASTER.index_of(t)] for t in truths])
    col = np.repeat(np.arange(COLUMNS), len(numbers)).astype(np.int32)
    return (
        col,
        np.tile(rows, COLUMNS),
        np.tile(np.asarray(numbers, dtype=np.int32), COLUMNS),
        np.tile(area, COLUMNS),
    )


#: The back's lines 40-48 numbered, a peak of the cloth's line 50 carried on as 49 (the
#: code at 49-54 and 50-55 differs in every ratio), the cloth's lines 51-55 unnumbered.
ERRING = ([*range(40, 50), -1, -1, -1, -1, -1], [*range(40, 49), *range(50, 56)])


def test_a_peak_one_line_off_its_column_s_reading_is_refused() -> None:
    col, row, number, area = _column(*ERRING)
    refused = misread_columns(col, row, number, area, RASTER)
    assert np.array_equal(refused, np.tile(np.arange(15) == 9, COLUMNS))


def test_the_reading_goes_up_the_column_as_well() -> None:
    """A cloth above the back: its lines 45-49 unnumbered, its line 50 carried on as 51
    with the back's lines 52-60 below, read upwards from the peak."""
    numbers = [-1] * 5 + list(range(51, 61))
    truths = [*range(45, 51), *range(52, 61)]
    col, row, number, area = _column(numbers, truths)
    refused = misread_columns(col, row, number, area, RASTER)
    assert np.array_equal(refused, np.tile(np.arange(15) == 5, COLUMNS))


def test_a_right_peak_beside_unnumbered_lines_it_reads_with_is_kept() -> None:
    col, row, number, area = _column(ERRING[0], list(range(40, 55)))
    assert not np.any(misread_columns(col, row, number, area, RASTER))


def test_a_peak_the_code_cannot_place_cleanly_is_kept() -> None:
    """Unnumbered peaks beyond whose brightness follows no shift of the code (a cloth's
    texture, shading): the code says nothing about the peak, and it keeps its number."""
    col, row, number, area = _column(*ERRING)
    rng = np.random.default_rng(3)
    beyond = (number < 0) | (np.arange(number.size) % 15 == 9)
    area = np.where(beyond, area * np.exp(rng.normal(0.0, 0.5, area.size)), area)
    assert not np.any(misread_columns(col, row, number, area, RASTER))


def test_too_short_a_reading_decides_nothing() -> None:
    """Two unnumbered peaks beyond the peak: two ratios, fewer than ``least``."""
    numbers, truths = ERRING
    col, row, number, area = _column(numbers[:12], truths[:12])
    assert not np.any(misread_columns(col, row, number, area, RASTER))
    assert np.any(misread_columns(col, row, number, area, RASTER, least=2))


def test_the_reading_stops_at_a_gap_off_one_spacing() -> None:
    """A gap of two spacings after the first unnumbered peak (a line unfound between): the
    reading holds two ratios and decides nothing."""
    numbers, truths = ERRING
    gaps = [SPACING] * 10 + [2.0 * SPACING] + [SPACING] * 3
    col, row, number, area = _column(numbers, truths, gaps=gaps)
    assert not np.any(misread_columns(col, row, number, area, RASTER))


def test_a_peak_with_no_numbered_neighbour_on_its_other_side_is_not_read() -> None:
    """The reading needs the numbered neighbour's gap as its spacing."""
    numbers, truths = ERRING
    col, row, number, area = _column(numbers[9:], truths[9:])
    assert not np.any(misread_columns(col, row, number, area, RASTER))


def test_switched_off_and_degenerate_inputs_refuse_nothing() -> None:
    col, row, number, area = _column(*ERRING)
    assert not np.any(misread_columns(col, row, number, area, RASTER, run=0))
    empty = np.zeros(0)
    assert (
        misread_columns(empty.astype(np.int32), empty, empty.astype(np.int32), empty, RASTER).size
        == 0
    )
    none = np.full(number.size, -1, dtype=np.int32)
    assert not np.any(misread_columns(col, row, none, area, RASTER))
    # a zero area reads as no ratio any shift explains
    dark = np.where(number < 0, 0.0, area)
    assert not np.any(misread_columns(col, row, number, dark, RASTER))


def test_numbers_beyond_the_raster_are_not_read() -> None:
    """A peak numbered at the raster's last line reads no line beyond it."""
    last = int(RASTER.numbers.max())
    numbers = [last - 1, last, -1, -1, -1, -1]
    col, row, number, area = _column(numbers, [last - 1, last, last, last, last, last])
    assert not np.any(misread_columns(col, row, number, area, RASTER))


def test_log_widths_by_number() -> None:
    table = log_width_by_number(RASTER)
    assert table.size == int(RASTER.numbers.max()) + 1
    assert np.isnan(table[0]) or RASTER.index_of(0) >= 0
    assert table[40] == pytest.approx(np.log(RASTER.widths[RASTER.index_of(40)]))


def test_parameters_are_validated() -> None:
    with pytest.raises(ValidationError):
        CodeWindowParams(reading_run=-1)
    with pytest.raises(ValidationError):
        CodeWindowParams(reading_clean=0.0)
    params = CodeWindowParams()
    assert (params.reading_run, params.reading_least) == (6, 3)
    assert (params.reading_margin, params.reading_clean) == (0.3, 0.2)
