"""Lines refused for their intensity ratios with column neighbours, and when they are spared."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
from rasterserver_plugins.code_evidence import area_ratio_of
from rasterserver_plugins.contradicted_pairs import refuse_contradicted_pairs
from rasterserver_plugins.numbering_params import CodeWindowParams
from rasterserver_plugins.numbering_refusals import (
    edge_doubts,
    faint_code,
    least_pair_departure,
    settle_last,
)

from rasterserver.errors import InputError
from rasterserver.raster import Raster, get_raster
from rasterserver.records_lines import OrderedLines

LAM = float(np.log(2.0))  # w8-1to2: heavy lines twice as wide as light ones


def _stack(
    extents: list[tuple[int, int]],
    gains: list[float],
    raster: Raster,
    seed: int = 3,
    heavy: float = 200.0,
    first: int = 0,
    shown: list[int] | None = None,
) -> tuple[OrderedLines, np.ndarray]:
    """Line ``i`` (raster line ``first + i``, row ``10 i``) over the columns ``extents[i]``,
    its areas those of its kind (light 100, ``heavy``) times ``gains[i]`` (an albedo edge, a
    shadow) with 3 % noise; one component, numbered ``first + i``. ``shown[i]``: the raster
    line whose kind line ``i`` shows (a line numbered off). Returns the lines and their
    numbers."""
    rng = np.random.default_rng(seed)
    cols, rows, lids, areas = [], [], [], []
    for i, ((c0, c1), gain) in enumerate(zip(extents, gains, strict=True)):
        c = np.arange(c0, c1)
        cols.append(c)
        rows.append(np.full(c.size, 10.0 * i))
        lids.append(np.full(c.size, i))
        kind_area = heavy if raster.code[first + i if shown is None else shown[i]] else 100.0
        areas.append(gain * kind_area * (1.0 + 0.03 * rng.standard_normal(c.size)))
    col, row, lid, area = (np.concatenate(a) for a in (cols, rows, lids, areas))
    order = np.lexsort((row, col))
    n = len(extents)
    line_order = np.arange(n, dtype=np.int32)
    data = OrderedLines(
        col=col[order].astype(np.int32),
        row=row[order],
        area=area[order].astype(np.float32),
        height=np.full(col.size, 40.0, np.float32),
        width=np.full(col.size, 5, np.int16),
        image_shape=np.array([100, 100]),
        line_id=lid[order].astype(np.int32),
        order=line_order[lid[order]],
        line_order=line_order,
        line_component=np.zeros(n, np.int32),
    )
    return data, raster.numbers[first : first + n].astype(np.int32)


def _refused(
    data: OrderedLines, numbers: np.ndarray, max_agreement: float, **shifts: Any
) -> set[int]:
    line_number = numbers.copy()
    per_line = np.bincount(data.line_id, minlength=numbers.size)
    refuse_contradicted_pairs(
        data,
        get_raster("w8-1to2"),
        LAM,
        line_number,
        per_line,
        max_agreement=max_agreement,
        **shifts,
    )
    return set(np.flatnonzero(line_number < 0).tolist())


def test_a_line_confirmed_on_its_other_side_is_spared() -> None:
    """A longer line three times as bright (an albedo edge) beside a short right line over
    10 columns: their pair contradicts the code. The short line's pair with the line below
    agrees over 30 columns, and that line agrees with the next: the short line is kept
    (refused when nothing is spared)."""
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(20, 60), (0, 30), (0, 60), (0, 60)], [3.0, 1.0, 1.0, 1.0], raster)
    assert _refused(data, numbers, 0.0) == {1}
    assert _refused(data, numbers, 0.4) == set()


def test_a_confirmation_over_fewer_columns_than_the_contradiction_does_not_count() -> None:
    """Contradicted over 30 columns, confirmed over 10: the short line is refused."""
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(0, 60), (0, 30), (20, 30), (20, 30)], [3.0, 1.0, 1.0, 1.0], raster)
    assert 1 in _refused(data, numbers, 0.4)


def test_a_confirmation_from_an_unconfirmed_neighbour_does_not_count() -> None:
    """The confirming line in a contradiction on its other side (a block placed off agrees
    with itself) or confirmed by nothing else (the last line): the short line is refused."""
    raster = get_raster("w8-1to2")
    extents = [(20, 60), (0, 30), (0, 60), (0, 60)]
    block, numbers = _stack(extents, [3.0, 1.0, 1.0, 3.0], raster)
    assert 1 in _refused(block, numbers, 0.4)
    last, numbers = _stack(extents[:3], [3.0, 1.0, 1.0], raster)
    assert _refused(last, numbers, 0.4) == {1}


def test_a_block_placed_a_line_off_does_not_confirm_itself() -> None:
    """Scene 7728 of the twin raster: behind a waistband the cloth's lines (twice as bright
    as the skin) are numbered one less than they are, their first line under the skin's
    last (line 18) agreeing with it by the albedo edge. The block's own pairs agree with the
    code at either placement but one: the pair of its first two lines, which would agree
    were both one more. The shorter line of that pair, confirmed below only by pairs that
    agree at either placement, is refused (version 22; version 21 spared it), and with
    ``shift_block`` the block's lines tied to it by such pairs go with it."""
    raster = get_raster("w8-1to2")
    extents = [(0, 40), (0, 28), (18, 40), (10, 40), (0, 40)]
    data, numbers = _stack(
        extents, [1.0, 2.0, 2.0, 2.0, 2.0], raster, first=18, shown=[18, 20, 21, 22, 23]
    )
    assert _refused(data, numbers, 0.4) == set()
    assert _refused(data, numbers, 0.4, shift_support=True) == {2}
    assert _refused(data, numbers, 0.4, shift_support=True, shift_block=40) == {2, 3, 4}
    # lines longer than shift_block stay; without shift_support there is no block
    assert _refused(data, numbers, 0.4, shift_support=True, shift_block=25) == {2}
    assert _refused(data, numbers, 0.4, shift_block=40) == set()


def test_a_right_block_keeps_its_confirmation() -> None:
    """The cloth's lines numbered right, twice as bright as the skin: their first line's
    pair with the skin's last contradicts the code (the albedo edge), and would agree were
    both one less; but the cloth's own pairs would contradict under that shift, so they
    confirm the line, which is kept as in version 21."""
    raster = get_raster("w8-1to2")
    extents = [(20, 60), (0, 30), (0, 60), (0, 60), (0, 60)]
    data, numbers = _stack(extents, [1.0, 2.0, 2.0, 2.0, 2.0], raster, first=18)
    assert _refused(data, numbers, 0.0) == {1}
    assert _refused(data, numbers, 0.4) == set()
    assert _refused(data, numbers, 0.4, shift_support=True, shift_block=40) == set()


def test_no_contradiction_refuses_nothing() -> None:
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(0, 30)] * 4, [1.0] * 4, raster)
    assert _refused(data, numbers, 0.0) == set()
    assert _refused(data, numbers, 0.4) == set()
    none = np.full(numbers.shape, -1, np.int32)
    per_line = np.bincount(data.line_id, minlength=4)
    assert refuse_contradicted_pairs(data, raster, LAM, none, per_line, max_agreement=0.4) == 0


def test_a_faint_code_doubts_only_the_codes_own_refusals() -> None:
    """With the 45:55 code (area ratio 1.22, below ``faint_ratio``) a line left unnumbered
    is no sign of trouble: only the lines the code refused are doubtful, among the faint
    share; with a clear code every unnumbered line is."""
    refused = np.array([False, True, False, False])
    line_number = np.array([5, -1, -1, 7], dtype=np.int32)
    params = CodeWindowParams()
    doubt, share = edge_doubts(refused, line_number, params, get_raster("w9-45to55"))
    assert doubt is not None and doubt.tolist() == [False, True, False, False]
    assert share == params.faint_share == 0.2
    doubt, share = edge_doubts(refused, line_number, params, get_raster("mseq7"))
    assert doubt is not None and doubt.tolist() == [False, True, True, False]
    assert share == params.block_share
    # version 15: no code is faint
    v15 = CodeWindowParams(faint_ratio=1.0)
    doubt, share = edge_doubts(refused, line_number, v15, get_raster("w9-45to55"))
    assert doubt is not None and doubt.tolist() == [False, True, True, False]
    assert share == v15.block_share
    # a ratio set by the user decides over the raster's widths
    clear = CodeWindowParams(area_ratio=1.5)
    assert edge_doubts(refused, line_number, clear, get_raster("w9-45to55"))[1] == 0.5


def test_the_block_edge_check_switched_off_doubts_nothing() -> None:
    refused = np.array([True, False])
    params = CodeWindowParams(block_edge_check=False)
    doubt, _ = edge_doubts(refused, np.array([-1, -1], dtype=np.int32), params, get_raster("mseq7"))
    assert doubt is None
    code = CodeWindowParams(doubtful="code")
    doubt, _ = edge_doubts(refused, np.array([-1, -1], dtype=np.int32), code, get_raster("mseq7"))
    assert doubt is not None and doubt.tolist() == [True, False]


def test_the_area_ratio_comes_from_the_rasters_widths_unless_set() -> None:
    assert area_ratio_of(get_raster("w8-1to2")) == pytest.approx(2.0)
    assert area_ratio_of(get_raster("w9-45to55")) == pytest.approx(1.1 / 0.9)
    assert area_ratio_of(get_raster("mseq7"), 1.8) == 1.8
    with pytest.raises(InputError, match="must exceed 1"):
        area_ratio_of(get_raster("mseq7"), 1.0)


def test_a_faint_code_needs_a_ratio_of_the_other_sign_to_refuse_a_pair() -> None:
    """Through the 45:55 code (log ratio 0.2) a short line one kind's difference off its
    neighbours (a shading or albedo step as large as the code's) is refused at a departure
    of 0.75, kept at the faint code's 1.5; a line two differences off (the ratio's sign
    flipped, as a piece placed a level off shows) is refused at either."""
    raster = get_raster("w9-45to55")
    lam = float(np.log(area_ratio_of(raster)))
    extents = [(0, 60), (0, 30), (0, 60), (0, 60)]

    def refused(step: float, min_departure: float) -> set[int]:
        data, numbers = _stack(
            extents, [1.0, np.exp(step * lam), 1.0, 1.0], raster, heavy=110 / 0.9
        )
        per_line = np.bincount(data.line_id, minlength=numbers.size)
        refuse_contradicted_pairs(data, raster, lam, numbers, per_line, min_departure=min_departure)
        return set(np.flatnonzero(numbers < 0).tolist())

    assert refused(1.0, 0.75) == {1}
    assert refused(1.0, 1.5) == set()
    assert refused(2.2, 1.5) == {1}
    assert refused(0.0, 0.75) == set()


def test_the_pair_departure_is_the_faint_codes_only_for_a_faint_code() -> None:
    params = CodeWindowParams()
    assert faint_code(get_raster("w9-45to55"), params)
    assert least_pair_departure(params, get_raster("w9-45to55")) == params.faint_departure == 1.5
    for name in ("default", "mseq7", "w8-1to2", "mseq8-35to65"):
        assert not faint_code(get_raster(name), params)
        assert least_pair_departure(params, get_raster(name)) == 0.75
    # version 16: the faint code's departure as the others'; version 15: no code is faint
    v16 = CodeWindowParams(faint_departure=0.75)
    assert least_pair_departure(v16, get_raster("w9-45to55")) == 0.75
    assert not faint_code(get_raster("w9-45to55"), CodeWindowParams(faint_ratio=1.0))


#: The last steps before the lone peaks and the column reading, switched off (so that a
#: test of those two sees only their own refusals).
LAST_STEPS_OFF = {
    "bracket_run": 0, "end_margin": 0, "end_dim": 0, "edge_run": 0, "surround_share": 0,
    "skip_ratio": 0, "detached_peaks": 0, "final_order": False,
}  # fmt: skip


def test_a_peak_left_with_no_numbered_column_neighbour_is_refused_last() -> None:
    """After the last steps (all off here) a numbered peak whose column neighbours are
    unnumbered is refused with ``final_isolated`` (version 18), kept without it or without
    the column check."""
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(0, 30), (0, 30), (0, 30)], [1.0, 1.0, 1.0], raster)
    number = numbers[data.line_id].copy()
    lonely = np.flatnonzero((data.col == 12) & (data.line_id == 1))
    number[(data.col == 12) & (data.line_id != 1)] = -1  # its column neighbours refused
    off = LAST_STEPS_OFF
    spacing = np.full(data.n_peaks, 10.0)
    got, notes = settle_last(data, number, spacing, CodeWindowParams(**off), raster)
    assert np.all(got[lonely] == -1) and np.sum(got != number) == lonely.size
    assert any("no numbered peak above or below" in n for n in notes)
    for switch in ({"final_isolated": False}, {"column_check": False}):
        kept, notes = settle_last(data, number, spacing, CodeWindowParams(**off, **switch), raster)
        assert np.array_equal(kept, number) and not notes


def test_a_short_line_numbered_by_one_neighbour_is_refused_last() -> None:
    """Line 3, four peaks below the back's line 2 over columns 10-13 and nothing numbered
    below it, is refused with ``one_sided_peaks`` (version 21), kept without it; the
    back's lines (30 peaks) are kept."""
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(0, 30), (0, 30), (0, 30), (10, 14)], [1.0] * 4, raster)
    number = numbers[data.line_id].copy()
    off = {**LAST_STEPS_OFF, "reading_run": 0, "block_least": 0, "final_isolated": False}
    spacing = np.full(data.n_peaks, 10.0)
    got, notes = settle_last(data, number, spacing, CodeWindowParams(**off), raster)
    assert np.array_equal(got != number, data.line_id == 3) and np.all(got[data.line_id == 3] == -1)
    assert any("one neighbour's contact" in n for n in notes)
    kept, notes = settle_last(
        data, number, spacing, CodeWindowParams(**off, one_sided_peaks=0), raster
    )
    assert np.array_equal(kept, number) and not notes


def test_a_block_its_columns_read_a_line_off_is_refused_last() -> None:
    """Lines 6-11 over columns 20-39 lie on a cloth (albedo 0.7) showing the next raster
    line at their rows, numbered with the back's lines (the lines run on onto it): the
    block is refused with ``block_least`` (version 20), kept without it; the back is
    kept."""
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(0, 40)] * 12, [1.0] * 12, raster)
    number = numbers[data.line_id].copy()
    cloth = (data.col >= 20) & (data.line_id >= 6)
    truth = np.where(cloth, data.line_id + 1, data.line_id)
    area = np.where(raster.code[truth] == 1, 200.0, 100.0) * np.where(cloth, 0.7, 1.0)
    data = dataclasses.replace(data, area=area.astype(np.float32))
    off = {**LAST_STEPS_OFF, "reading_run": 0, "final_isolated": False}
    spacing = np.full(data.n_peaks, 10.0)
    got, notes = settle_last(data, number, spacing, CodeWindowParams(**off), raster)
    refused = got != number
    assert np.any(refused) and not np.any(refused & ~cloth) and np.all(got[refused] == -1)
    assert refused[cloth & (data.line_id >= 7)].mean() > 0.9
    assert any("read the code" in n or "reads the code" in n for n in notes)
    kept, notes = settle_last(data, number, spacing, CodeWindowParams(**off, block_least=0), raster)
    assert np.array_equal(kept, number) and not notes


def test_a_peak_its_column_reads_a_line_off_is_refused_last() -> None:
    """Line 3 carried on one low (a line's end run onto a cloth) above the unnumbered lines
    4-9, whose brightness follows the code at their true numbers: refused with
    ``reading_run`` (version 19), kept without it; the right lines above are kept."""
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(0, 30)] * 10, [1.0] * 10, raster)
    number = numbers[data.line_id].copy()
    number[data.line_id >= 4] = -1  # the cloth's lines, refused for their order
    carried = data.line_id == 3
    number[carried] -= 1
    off = LAST_STEPS_OFF
    spacing = np.full(data.n_peaks, 10.0)
    got, notes = settle_last(data, number, spacing, CodeWindowParams(**off), raster)
    assert np.all(got[carried] == -1) and np.array_equal(got[~carried], number[~carried])
    assert any("read on through the unnumbered peaks" in n for n in notes)
    kept, notes = settle_last(data, number, spacing, CodeWindowParams(**off, reading_run=0), raster)
    assert np.array_equal(kept, number) and not notes
    # numbered right, line 3 reads the code at its own number: kept
    number[carried] += 1
    right, notes = settle_last(data, number, spacing, CodeWindowParams(**off), raster)
    assert np.array_equal(right, number) and not notes


def test_numbers_out_of_order_in_a_column_are_refused_last() -> None:
    """Line 3 numbered as line 2 (a line's start carried onto another surface's line): both
    lines' peaks are refused with ``final_order`` (version 25), as the column cannot tell
    which of the two is off; kept without it; the lines in order are kept."""
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(0, 30)] * 4, [1.0] * 4, raster)
    number = numbers[data.line_id].copy()
    twins = np.isin(data.line_id, [2, 3])
    number[data.line_id == 3] = number[data.line_id == 2][0]
    off = {k: v for k, v in LAST_STEPS_OFF.items() if k != "final_order"}
    spacing = np.full(data.n_peaks, 10.0)
    params = CodeWindowParams(**off, final_isolated=False)
    got, notes = settle_last(data, number, spacing, params, raster)
    assert np.all(got[twins] == -1) and np.array_equal(got[~twins], number[~twins])
    assert any("do not increase down their column" in n for n in notes)
    params = CodeWindowParams(**off, final_isolated=False, final_order=False)
    kept, notes = settle_last(data, number, spacing, params, raster)
    assert np.array_equal(kept, number) and not notes


def test_a_lone_numbered_peak_between_its_lines_refused_peaks_is_refused_last() -> None:
    """With ``final_run`` 2 (an option, off) a single numbered peak left between refused
    peaks of its own line after the last steps is refused (its number rests on the line's
    continuity through refused peaks alone); runs of two are kept, and nothing without it."""
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(0, 30), (0, 30), (0, 30)], [1.0, 1.0, 1.0], raster)
    number = numbers[data.line_id].copy()
    middle = data.line_id == 1
    number[middle & (data.col >= 10) & (data.col <= 20)] = -1  # refused around ...
    lone = np.flatnonzero(middle & (data.col == 15))
    number[lone] = numbers[1]  # ... one numbered peak left among them
    pair = np.flatnonzero(middle & (data.col >= 17) & (data.col <= 18))
    number[pair] = numbers[1]  # and a run of two
    spacing = np.full(data.n_peaks, 10.0)
    off = CodeWindowParams(**LAST_STEPS_OFF, final_isolated=False)
    got, notes = settle_last(data, number, spacing, off.model_copy(update={"final_run": 2}), raster)
    assert np.all(got[lone] == -1) and np.all(got[pair] == numbers[1])
    assert np.sum(got != number) == lone.size
    assert any("cut off by the peaks the last steps refused" in n for n in notes)
    kept, notes = settle_last(data, number, spacing, off, raster)
    assert np.array_equal(kept, number) and not notes


def test_the_line_end_options_are_off_and_checked() -> None:
    """The options tried as versions 26-28 are off by default, but for ``meet_tolerance``,
    one of version 29's steps; a brightness step of a factor of 1 or less would call every
    end a step and is rejected."""
    params = CodeWindowParams()
    assert (params.meet_tolerance, params.end_jump, params.final_run) == (1.0, 0.0, 0)
    assert (params.course_beyond, params.course_departure) == (0.0, 1.0)
    assert (params.block_gain, params.block_gain_share) == (0.3, 0.0)
    with pytest.raises(ValueError, match="block_gain_share"):
        CodeWindowParams(block_gain_share=-0.1)
    for bad in (0.5, 1.0):
        with pytest.raises(ValueError, match="end_jump"):
            CodeWindowParams(end_jump=bad)
    assert CodeWindowParams(end_jump=2.8).end_jump == 2.8


def test_a_line_s_end_turned_onto_its_refused_peaks_course_is_refused_with_the_option() -> None:
    """With ``course_beyond`` 0.4 (an option, off) the three numbered peaks at line 1's end
    that lie on the course of its refused peaks beyond them, two rows off its own course,
    are refused, and nothing else; nothing without it."""
    raster = get_raster("w8-1to2")
    data, numbers = _stack([(0, 30)] * 3, [1.0] * 3, raster)
    turned = (data.line_id == 1) & (data.col >= 22)
    data = dataclasses.replace(data, row=np.where(turned, data.row + 2.0, data.row))
    number = numbers[data.line_id].copy()
    number[(data.line_id == 1) & (data.col >= 25)] = -1  # the far part, refused
    spacing = np.full(data.n_peaks, 10.0)
    off = CodeWindowParams(**LAST_STEPS_OFF, final_isolated=False)
    got, notes = settle_last(data, number, spacing, off.model_copy(update={"course_beyond": 0.4}),
                             raster)  # fmt: skip
    assert np.flatnonzero(got != number).tolist() == np.flatnonzero(turned & (number >= 0)).tolist()
    assert np.sum(turned & (number >= 0)) == 3
    assert any("on the course of its refused peaks beyond" in n for n in notes)
    kept, notes = settle_last(data, number, spacing, off, raster)
    assert np.array_equal(kept, number) and not notes
