"""Blocks of numbered peaks whose own columns read the code a line off: refused."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from rasterserver_plugins.column_blocks import code_contrast, contradicted_blocks
from rasterserver_plugins.numbering_params import CodeWindowParams

from rasterserver.raster import Raster, default_raster, get_raster, w9_faint_raster

RASTER = default_raster()
FIRST = 40  # the first line's number
LINES = 16
COLUMNS = 60


def _scene(
    cloth_columns: range = range(40, 60),
    cloth_lines: range = range(8, 16),
    numbered_right: bool = False,
    seed: int = 5,
    raster: Raster = RASTER,
    alternate: bool = False,
) -> tuple[np.ndarray, ...]:
    """Lines ``FIRST ..`` one spacing apart over ``COLUMNS`` columns; in ``cloth_columns``,
    lines ``cloth_lines`` lie on a cloth (albedo 0.7) that shows the next raster line at
    their rows, numbered with the back's line (``numbered_right``: with the cloth's).
    Areas are the code's widths with 3 % noise; ``alternate``: the cloth's odd columns
    show the previous raster line instead (a patch reading off both ways, as noise does).
    Returns col, number, line_id, area (sorted by ``(col, row)``) and the truth."""
    rng = np.random.default_rng(seed)
    col = np.repeat(np.arange(COLUMNS), LINES)
    line = np.tile(np.arange(LINES), COLUMNS)
    cloth = np.isin(col, cloth_columns) & np.isin(line, cloth_lines)
    truth = FIRST + line + np.where(alternate & (col % 2 == 1), -1, 1) * cloth
    width = np.array([raster.widths[raster.index_of(int(t))] for t in truth])
    area = 100.0 * width * np.where(cloth, 0.7, 1.0) * (1.0 + 0.03 * rng.standard_normal(col.size))
    number = truth if numbered_right else FIRST + line
    return col, number.astype(np.int32), line.astype(np.int32), area, truth


def test_a_cloth_block_numbered_a_line_off_is_refused() -> None:
    col, number, line_id, area, truth = _scene()
    refused = contradicted_blocks(col, number, line_id, area, RASTER)
    wrong = number != truth
    assert np.any(refused)
    assert not np.any(refused & ~wrong)  # no peak of the back
    # the cloth's inner lines, read within the cloth on both sides, all go
    inner = wrong & np.isin(line_id, range(9, 15))
    assert refused[inner].mean() > 0.9


def test_the_same_block_numbered_right_is_kept() -> None:
    col, number, line_id, area, _ = _scene(numbered_right=True)
    assert not np.any(contradicted_blocks(col, number, line_id, area, RASTER))


def test_code_contrast_is_the_log_ratio_of_the_kinds_widths() -> None:
    assert code_contrast(w9_faint_raster()) == pytest.approx(np.log(55 / 45))
    assert code_contrast(get_raster("w8-1to2")) == pytest.approx(np.log(2))
    assert code_contrast(RASTER) == pytest.approx(np.log(1.5))


def test_a_faint_code_s_block_needs_the_gain_as_a_share_of_its_contrast() -> None:
    """Through the faint 45:55 code a shifted reading gains at most 2 x 0.20 per ratio,
    and only where two kinds swap: few peaks reach ``gain`` 0.3, too few for a block (the
    arm of scene 69807). With the gain at 0.4 of the code's contrast (and blocks of one
    shift) the block goes, and still no peak of the back; numbered right, nothing goes."""
    faint = w9_faint_raster()
    col, number, line_id, area, truth = _scene(raster=faint, seed=7)
    assert not np.any(contradicted_blocks(col, number, line_id, area, faint))
    refused = contradicted_blocks(col, number, line_id, area, faint, gain_share=0.4, one_shift=True)
    wrong = number != truth
    assert not np.any(refused & ~wrong)
    # a line whose column neighbours keep their kinds under the shift offers no reading
    # (a third of this code's cloth lines); the later steps judge what the block leaves
    assert refused[wrong & np.isin(line_id, range(9, 15))].mean() > 0.6
    col, number, line_id, area, _ = _scene(raster=faint, seed=7, numbered_right=True)
    assert not np.any(
        contradicted_blocks(col, number, line_id, area, faint, gain_share=0.4, one_shift=True)
    )


def test_the_gain_share_leaves_a_code_of_ample_contrast_as_the_gain_does() -> None:
    """``gain_share`` 0.74 of the default code's contrast log 1.5 is ``gain`` 0.3."""
    col, number, line_id, area, _ = _scene()
    assert np.array_equal(
        contradicted_blocks(col, number, line_id, area, RASTER),
        contradicted_blocks(col, number, line_id, area, RASTER, gain_share=0.3 / np.log(1.5)),
    )


def test_one_shift_keeps_a_cloth_block_and_parts_a_block_of_mixed_shifts() -> None:
    """With ``one_shift`` a block is joined from peaks supporting one shift only. Over the
    first eight lines, a cloth (all a line off the same way) is refused; a patch whose
    columns read off alternately up and down is one block of mixed shifts, refused
    without it and kept with it (each shift's peaks are single columns, fewer than
    ``least``). Over lines where the code alternates light and heavy, one reading fits both
    shifts, and the default cloth's block is the same either way."""
    top = range(0, 8)
    col, number, line_id, area, truth = _scene(cloth_lines=top)
    refused = contradicted_blocks(col, number, line_id, area, RASTER, one_shift=True)
    assert np.any(refused) and not np.any(refused & (number == truth))
    col, number, line_id, area, _ = _scene(cloth_lines=top, alternate=True)
    assert np.any(contradicted_blocks(col, number, line_id, area, RASTER))
    assert not np.any(contradicted_blocks(col, number, line_id, area, RASTER, one_shift=True))
    col, number, line_id, area, _ = _scene()
    np.testing.assert_array_equal(
        contradicted_blocks(col, number, line_id, area, RASTER, one_shift=True),
        contradicted_blocks(col, number, line_id, area, RASTER),
    )


def test_a_block_smaller_than_least_is_kept() -> None:
    """Two columns of six cloth lines: too few peaks to outweigh a fold's or a shadow's
    noise."""
    col, number, line_id, area, _ = _scene(cloth_columns=range(58, 60), cloth_lines=range(10, 16))
    assert not np.any(contradicted_blocks(col, number, line_id, area, RASTER))
    assert np.any(contradicted_blocks(col, number, line_id, area, RASTER, least=5))


def test_a_block_holding_no_line_s_end_is_kept() -> None:
    """The same reading in the lines' middle: the lines run on both sides of it, numbered
    right (a patch of another albedo reads off only by chance); not refused."""
    col, number, line_id, area, _ = _scene(cloth_columns=range(20, 40))
    assert not np.any(contradicted_blocks(col, number, line_id, area, RASTER))


def test_a_block_holding_one_line_s_end_is_kept() -> None:
    """The reading off across the lines' middle, where one short line ends inside it (a
    dim patch of the back under the raster's top lines): one line's end is not a cloth the
    lines run onto; kept, refused with ``ends_least`` 1."""
    col, number, line_id, area, _ = _scene(cloth_columns=range(20, 40))
    short = (line_id == 12) & (col >= 30)
    keep = ~short
    col, number, line_id, area = col[keep], number[keep], line_id[keep], area[keep]
    assert not np.any(contradicted_blocks(col, number, line_id, area, RASTER))
    assert np.any(contradicted_blocks(col, number, line_id, area, RASTER, ends_least=1))


def test_peaks_read_only_with_unnumbered_neighbours_are_not_read() -> None:
    """Every other line unnumbered: no column pair of numbers one apart, nothing read."""
    col, number, line_id, area, _ = _scene()
    number = np.where(line_id % 2 == 1, -1, number).astype(np.int32)
    assert not np.any(contradicted_blocks(col, number, line_id, area, RASTER))


def test_degenerate_inputs() -> None:
    col, number, line_id, area, _ = _scene()
    assert not np.any(contradicted_blocks(col, number, line_id, area, RASTER, least=0))
    empty = np.zeros(0)
    assert contradicted_blocks(empty, empty, empty, empty, RASTER).shape == (0,)
    none = np.full(number.size, -1)
    assert not np.any(contradicted_blocks(col, none, line_id, area, RASTER))
    # zero areas read as -inf: no shift explains them, nothing refused, no warning
    zero = np.zeros(area.size)
    with np.errstate(all="raise"):
        assert not np.any(contradicted_blocks(col, number, line_id, zero, RASTER))
    # numbers beyond the raster's last line: those shifts read nothing
    beyond = number + RASTER.n_lines
    assert not np.any(contradicted_blocks(col, beyond, line_id, area, RASTER))


def test_parameters_are_validated() -> None:
    with pytest.raises(ValidationError):
        CodeWindowParams(block_least=-1)
    with pytest.raises(ValidationError):
        CodeWindowParams(block_clean=0)
    with pytest.raises(ValidationError):
        CodeWindowParams(block_gain=-0.1)
    with pytest.raises(ValidationError):
        CodeWindowParams(block_ends=0)
    params = CodeWindowParams()
    assert (params.block_least, params.block_gain, params.block_clean) == (15, 0.3, 0.15)
    assert params.block_ends == 2


def _support_by_whole_arrays(number, step, pair, table, gain, clean, shifts):  # type: ignore[no-untyped-def]
    """The shifts each peak supports as the first form of the step computed them: one
    pass over all column pairs per shift (``(n, 2 * shifts)``, shifts ``-shifts .. -1,
    1 .. shifts``)."""
    n = number.size

    def costs(shift: int) -> np.ndarray:
        lo, hi = number[:-1] + shift, number[1:] + shift
        inside = (np.minimum(lo, hi) >= 0) & (np.maximum(lo, hi) < table.size)
        expected = np.full(n - 1, np.nan)
        ok = pair & inside
        expected[ok] = table[hi[ok]] - table[lo[ok]]
        with np.errstate(invalid="ignore"):
            cost = np.abs(step - expected)
        cost = np.where(pair, np.where(np.isnan(cost), np.inf, cost), 0.0)
        out = np.zeros(n)
        out[:-1] += cost
        out[1:] += cost
        return out

    ratios = np.zeros(n)
    ratios[:-1] += pair
    ratios[1:] += pair
    per = np.maximum(ratios, 1)
    own = costs(0)
    support = []
    for shift in [s for s in range(-shifts, shifts + 1) if s]:
        cost = costs(shift)
        with np.errstate(invalid="ignore"):
            support.append((ratios > 0) & (cost <= clean * per) & ((own - cost) >= gain * per))
    return np.stack(support, axis=1)


@pytest.mark.parametrize("seed", range(12))
def test_the_compiled_reading_decides_as_whole_array_passes(seed: int) -> None:
    from rasterserver_plugins.check_scans import block_support_flags
    from rasterserver_plugins.column_reading import log_width_by_number

    rng = np.random.default_rng(seed)
    col, number, _, area, _ = _scene(seed=seed)
    number = np.where(rng.random(number.size) < 0.1, -1, number).astype(np.int64)
    number = np.where(rng.random(number.size) < 0.02, number + 3, number)  # gaps in numbers
    area = area * np.exp(rng.normal(0.0, 0.3, area.size))
    area[rng.random(area.size) < 0.01] = 0.0
    pair = (
        (col[:-1] == col[1:])
        & (number[:-1] >= 0)
        & (number[1:] >= 0)
        & (np.abs(number[1:] - number[:-1]) == 1)
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        log_area = np.log(area)
        step = log_area[1:] - log_area[:-1]
    table = log_width_by_number(RASTER)
    for gain, clean, shifts in ((0.3, 0.15, 2), (0.1, 0.3, 1), (0.0, 0.5, 3)):
        expected = _support_by_whole_arrays(number, step, pair, table, gain, clean, shifts)
        every = block_support_flags(number, step, pair, table, gain, clean, shifts, True)
        np.testing.assert_array_equal(every, expected)
        anyone = block_support_flags(number, step, pair, table, gain, clean, shifts, False)
        np.testing.assert_array_equal(anyone, expected.any(axis=1, keepdims=True))
