"""Line numbering against the simulator's ground truth, with misread and short components."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from image_truth import back, rendering_raster, truth_lines, truth_of_peaks, wall
from rasterserver_plugins.line_numbering import CodeWindowNumbering
from rasterserver_plugins.line_search import HierarchicalLineSearch
from rasterserver_plugins.line_sequence import HierarchicalLineOrder
from rasterserver_plugins.peak_detection import VERSION_5, FirstMomentPeaks

from rasterserver.errors import InputError
from rasterserver.records import Image
from rasterserver.records_lines import NumberedLines, OrderedLines
from rasterserver.stage import StageContext, run_stage

#: The peaks of version 5 in version 6 (the extrema found on ``[1, 2, 1]``-smoothed columns,
#: the heights over 3.5 times the frame's noise): the scenes below were found and judged
#: with them. Version 6 finds other peaks where lines crowd and at dim line ends, and the
#: line ends those cases turn on move with them; their tests compare the numbering's
#: versions on version 5's peaks and check the installed chain besides.
PEAKS_5 = VERSION_5
#: The peaks of version 4 in version 6 (no flanked peaks kept, version 5's extrema): the
#: frames of the scenes below were judged with them when their cases were found.
PEAKS_4 = {"flank_tolerance": 0.0, **PEAKS_5}
#: The line order's staircase option (lines overlapping only by their ends over a few
#: columns are not neighbours; tried as order version 2, not adopted).
STAIRCASE = {"end_overlaps_link": False}
#: The line search of version 2 in version 3 (no turn cuts, the vertex of a corner kept):
#: the scenes below whose line ends ran onto another surface's line were found under it.
LINES_2 = {"turn": None, "vertex": False}
#: The line order of version 1 in version 3 (a column's pair counted as neighbours up to 1.6
#: times the gaps beside it): the scenes below erred under it, and version 3 orders several
#: of them right, so that the earlier numbering does not err there. Their tests compare the
#: numbering's versions with it and check the installed chain besides.
ORDER_1 = {"gap_ratio": 1.6}


def _on_peaks_5(params: dict) -> dict:
    """The stage parameters ``params`` on version 5's peaks (unless they set the peaks)."""
    return {"peaks": PEAKS_5, **params}


#: Version 29's parameters (version 30's check of a bracketed run against its peaks' lines
#: switched off).
V29 = {"bracket_line": False}
#: Version 25's parameters (the line-end steps of version 29 switched off; 26-28 were not
#: adopted): the scenes below whose line ends erred were found under it.
V25 = {**V29, "meet_tolerance": 0.0, "outer_gap": 0.0, "one_sided_peaks": 5}
#: Version 23's parameters (the steps of 25 and 29 switched off; 24 was not adopted).
V23 = {**V25, "final_order": False}
#: Version 22's parameters in version 25 (the steps of 23 and 25 switched off).
V22 = {"linked_one_sided": 0, **V23}
#: The kinked-ends option (``kink_bend``, tried as version 24, not adopted) switched on.
KINKED = {"kink_bend": 0.8}
#: Version 21's parameters in version 25 (the steps of 22-25 switched off).
V21 = {"pair_shift": False, "shift_block": 0, **V22}
#: Version 20's parameters in version 25 (the steps of 21-25 switched off).
V20 = {**V21, "one_sided_peaks": 0}
#: Version 19's parameters in version 25 (the steps of 20-25 switched off).
V19 = {"block_least": 0, **V20}
#: Version 18's parameters in version 25 (the steps of 19-25 switched off).
V18 = {"reading_run": 0, **V19}
#: Version 17's parameters in version 25 (the steps of 18-25 switched off).
V17 = {"poor_run_factor": 2.0, "final_isolated": False, **V18}
#: The steps of versions 13-25 switched off: part of every emulation of an earlier
#: version (each would otherwise refuse what the earlier one erred on).
STEPS_13_21_OFF = {
    "surround_share": 0.0,
    "skip_ratio": 0.0,
    "detached_peaks": 0,
    "faint_ratio": 1.0,
    **V17,
}


def _context() -> StageContext:
    return StageContext(raster=rendering_raster())


def _chain(pixels: np.ndarray) -> NumberedLines:
    peaks = run_stage(FirstMomentPeaks, Image(pixels))
    ordered = run_stage(HierarchicalLineOrder, run_stage(HierarchicalLineSearch, peaks))
    return run_stage(CodeWindowNumbering, ordered, context=_context())


def _ordered_truth(
    col: np.ndarray, row: np.ndarray, area: np.ndarray, number: np.ndarray
) -> OrderedLines:
    """Ordered lines straight from the truth: one line per raster line, one component."""
    numbers, line_id = np.unique(number, return_inverse=True)
    order = (numbers - numbers.min()).astype(np.int32)
    n = col.size
    return OrderedLines(
        col=col,
        row=row,
        area=area,
        height=np.full(n, 40.0, np.float32),
        width=np.full(n, 7, np.int16),
        image_shape=np.array([604, 576]),
        line_id=line_id.astype(np.int32),
        order=order[line_id],
        line_order=order,
        line_component=np.zeros(numbers.size, np.int32),
    )


def _assert_numbered_right(result: NumberedLines, number: np.ndarray, refused: int = 30) -> None:
    """Every numbered peak right, at most ``refused`` left unnumbered: truth lines join the
    trunk and the arm at the shoulders, where the line jumps by a spacing (version 4 refuses
    the peaks there, version 6 their column neighbours and the short runs between them).
    The lines leaving the frame's top or bottom edge lose their last columns there (version
    12), within 1.5 line spacings of the edge, up to six peaks at each end of a line."""
    from rasterserver_plugins.numbering_checks import local_spacing

    numbered = result.number >= 0
    assert np.array_equal(result.number[numbered], number[numbered])
    spacing = local_spacing(result.col, result.row, number)
    rows = int(result.image_shape[0])
    edge = (result.row < 1.5 * spacing) | (rows - 1 - result.row < 1.5 * spacing)
    assert np.count_nonzero(~numbered & ~edge) <= refused
    assert np.count_nonzero(~numbered & edge) <= 2 * 6 * np.unique(result.line_id).size


def _wrong_and_numbered(result: NumberedLines, number: np.ndarray) -> tuple[int, int]:
    wrong = numbered = 0
    for line in range(result.line_order.size):
        truth = number[(result.line_id == line) & (number >= 0)]
        if result.line_number[line] >= 0 and truth.size:
            numbered += 1
            wrong += int(np.bincount(truth).argmax() != result.line_number[line])
    return wrong, numbered


@pytest.mark.parametrize("name", ["normal", "severe"])
def test_simulated_back_is_numbered_correctly(name: str) -> None:
    r = back(name)
    result = _chain(r.image)
    number, _ = truth_of_peaks(result.col, result.row, r.line_rows)
    wrong, numbered = _wrong_and_numbered(result, number)
    assert wrong == 0
    assert numbered > 100
    # coverage: peaks on true lines that got a number
    assert np.mean(result.number[number >= 0] >= 0) > 0.98
    # and the numbers are the true ones, peak by peak
    both = (number >= 0) & (result.number >= 0)
    assert np.array_equal(result.number[both], number[both])
    assert result.confidence > 0.5


def test_flat_wall_is_numbered_correctly() -> None:
    r = wall()
    result = _chain(r.image)
    number, _ = truth_of_peaks(result.col, result.row, r.line_rows)
    wrong, numbered = _wrong_and_numbered(result, number)
    assert wrong == 0 and numbered >= 55
    # the wall fills the frame: the lines leaving its top or bottom edge lose the last
    # columns there (version 12), nothing else is refused
    notes = [n for n in result.reason.split("; ") if n and "too few lines" not in n]
    assert all("leaving the frame's top or bottom edge" in n for n in notes)
    assert int(notes[0].split()[0]) <= 2 * 6 * 4 if notes else True


def test_observed_kinds_follow_the_code() -> None:
    r = back("normal")
    result = _chain(r.image)
    raster = rendering_raster()
    numbered = result.line_number >= 0
    expected = raster.code[result.line_number[numbered] - raster.numbers[0]]
    observed = result.kind_observed[numbered]
    known = observed >= 0
    assert known.mean() > 0.9
    assert np.mean(observed[known] == expected[known]) > 0.97


def test_truth_lines_are_numbered() -> None:
    col, row, area, number = truth_lines(back("normal"))
    result = run_stage(
        CodeWindowNumbering, _ordered_truth(col, row, area, number), context=_context()
    )
    # one "line" per raster line joins surfaces at the shoulders, where the real line jumps
    # by a spacing: those few peaks are refused (version 4), with their column neighbours
    # and the short runs between them (version 6: 8 more), nothing else
    _assert_numbered_right(result, number)
    assert result.reason == "" or "line jumps" in result.reason


@pytest.mark.parametrize("which", [5, 20, 40])
def test_one_swapped_kind_still_numbers_correctly(which: int) -> None:
    col, row, area, number = truth_lines(back("normal"))
    numbers = np.unique(number)
    target = numbers[which]
    raster = rendering_raster()
    heavy = raster.code[raster.index_of(int(target))] == 1
    # misread: the line's intensity as if it were of the other kind
    area = np.where(number == target, area / 1.5 if heavy else area * 1.5, area).astype(np.float32)
    result = run_stage(
        CodeWindowNumbering, _ordered_truth(col, row, area, number), context=_context()
    )
    # the component is numbered right; the misread line's ratios with its neighbours
    # contradict the code there, so it or a neighbour may be refused (version 4), never
    # numbered wrongly
    numbered = result.number >= 0
    assert np.array_equal(result.number[numbered], number[numbered])
    assert np.count_nonzero(result.line_number < 0) <= 2
    line = np.flatnonzero(np.unique(number) == target)[0]
    assert result.kind_observed[line] in (-1, 0 if heavy else 1)


def test_component_too_short_to_be_unique_is_left_unnumbered() -> None:
    col, row, area, number = truth_lines(back("normal"))
    numbers = np.unique(number)
    keep = np.isin(number, numbers[20:26])  # 6 lines, fewer than the window of 9
    result = run_stage(
        CodeWindowNumbering,
        _ordered_truth(col[keep], row[keep], area[keep], number[keep]),
        context=_context(),
    )
    assert np.all(result.number == -1) and np.all(result.line_number == -1)
    assert result.confidence == 0.0
    assert "too few lines" in result.reason


def test_ambiguous_component_is_refused() -> None:
    col, row, _area, number = truth_lines(back("normal"))
    numbers = np.unique(number)
    keep = np.isin(number, numbers[10:22])  # 12 lines ...
    flat = np.full(int(keep.sum()), 100.0, np.float32)  # ... all of one apparent kind
    result = run_stage(
        CodeWindowNumbering,
        _ordered_truth(col[keep], row[keep], flat, number[keep]),
        context=_context(),
    )
    assert np.all(result.number == -1)
    assert result.reason


@pytest.mark.parametrize(
    "pixels",
    [
        np.zeros((604, 576), np.uint8),
        np.full((604, 576), 255, np.uint8),
        np.full((604, 576), 80, np.uint8),
        np.zeros((1, 576), np.uint8),
        np.full((604, 1), 30, np.uint8),
        np.zeros((1, 1), np.uint8),
    ],
    ids=["black", "saturated", "uniform", "1-row", "1-column", "1x1"],
)
def test_degenerate_images_give_an_empty_result_with_a_reason(pixels: np.ndarray) -> None:
    result = _chain(pixels)
    assert result.n_peaks == 0 and result.line_number.size == 0
    assert result.reason and result.confidence == 0.0


def test_raster_is_required() -> None:
    ordered = _ordered_truth(
        np.arange(3, dtype=np.int32), np.ones(3), np.ones(3, np.float32), np.ones(3, np.int64)
    )
    with pytest.raises(InputError, match="raster"):
        run_stage(CodeWindowNumbering, ordered)
    with pytest.raises(InputError, match="Raster"):
        run_stage(CodeWindowNumbering, ordered, context=StageContext(raster="default"))


def test_numbers_come_from_the_raster_definition() -> None:
    from rasterserver.raster import DEFAULT_CODE, make_raster

    col, row, area, number = truth_lines(back("normal"))
    shifted = make_raster(code=DEFAULT_CODE, first_number=101)
    result = run_stage(
        CodeWindowNumbering,
        _ordered_truth(col, row, area, number),
        context=StageContext(raster=shifted),
    )
    _assert_numbered_right(result, number + 100)


def test_min_lines_parameter() -> None:
    col, row, area, number = truth_lines(back("normal"))
    numbers = np.unique(number)
    keep = np.isin(number, numbers[20:32])  # 12 lines
    ordered = _ordered_truth(col[keep], row[keep], area[keep], number[keep])
    numbered = run_stage(CodeWindowNumbering, ordered, context=_context())
    _assert_numbered_right(numbered, number[keep])
    refused = run_stage(CodeWindowNumbering, ordered, {"min_lines": 13}, context=_context())
    assert np.all(refused.number == -1) and "too few lines" in refused.reason


def test_shifted_block_inside_a_component_is_refused_not_misnumbered() -> None:
    """Line sequence put the lower lines one level off (as at a waistband): the old,
    code-only numbering gives them wrong numbers, version 2 leaves them unnumbered."""
    from rasterserver_plugins.line_numbering import number_lines

    col, row, area, number = truth_lines(back("normal"))
    ordered = _ordered_truth(col, row, area, number)
    numbers = np.unique(number)
    cut = numbers[-16]
    shifted = ordered.line_order.copy()
    shifted[numbers >= cut] += 1  # a line taken for missing: every lower line one level off
    bad = OrderedLines(
        **{**ordered.__dict__, "line_order": shifted, "order": shifted[ordered.line_id]}
    )
    raster = rendering_raster()
    _, _, comps = number_lines(bad, raster)
    assert comps[0].offset >= 0  # the component as a whole reads clearly
    # the naive reading: that one offset for the whole component, the lower block all wrong
    naive = raster.numbers[np.minimum(comps[0].offset + shifted, raster.n_lines - 1)]
    naive_wrong = naive != numbers
    result = run_stage(CodeWindowNumbering, bad, context=_context())
    wrong = (result.line_number >= 0) & (result.line_number != numbers)
    assert naive_wrong.sum() >= 10
    assert wrong.sum() == 0
    assert np.count_nonzero(result.line_number >= 0) > 30
    assert "contradicts" in result.reason or "order" in result.reason


def test_touching_component_with_contradicting_code_is_refused() -> None:
    """A small component whose code reads one line off against the numbered trunk it
    continues: the contacts contradict it, so it stays unnumbered with the reason."""
    col, row, area, number = truth_lines(back("normal"))
    numbers = np.unique(number)
    ordered = _ordered_truth(col, row, area, number)
    # split: the right part (col >= 400) of lines 20..34 becomes component 1, and its areas
    # are those of the lines one below (a misreading of the whole piece by one line)
    line_of = ordered.line_id
    piece = (col >= 400) & np.isin(number, numbers[20:35])
    n_lines = numbers.size
    new_line = np.where(piece, n_lines + (line_of - 20), line_of)
    line_order = np.concatenate([ordered.line_order, np.arange(15)]).astype(np.int32)
    line_comp = np.concatenate([ordered.line_component, np.ones(15, np.int32)]).astype(np.int32)
    area2 = area.copy()
    for k in range(15):
        src = (number == numbers[21 + k]) & ~piece
        dst = piece & (number == numbers[20 + k])
        if src.any() and dst.any():
            area2[dst] = np.median(area[src])
    order = np.lexsort((row, col))
    sel = lambda a: a[order]  # noqa: E731
    data = OrderedLines(
        col=sel(col),
        row=sel(row),
        area=sel(area2).astype(np.float32),
        height=np.full(col.size, 40.0, np.float32),
        width=np.full(col.size, 7, np.int16),
        image_shape=np.array([604, 576]),
        line_id=sel(new_line).astype(np.int32),
        order=line_order[sel(new_line)],
        line_order=line_order,
        line_component=line_comp,
    )
    result = run_stage(CodeWindowNumbering, data, context=_context())
    truth = sel(number)
    assert np.all(result.number[(result.number >= 0)] == truth[result.number >= 0])
    assert np.all(result.line_number[n_lines:] == -1)


@pytest.mark.parametrize("name", ["mseq7", "w8-1to2", "w9-45to55", "mseq8-35to65"])
def test_clinic_codes_number_truth_lines(name: str) -> None:
    """Truth lines of a flat wall under each clinic raster (and the one held out from
    tuning): numbered from the raster's own width ratio, and never wrongly."""
    from rasterserver.raster import get_raster

    raster = get_raster(name)
    n = 40
    first = 30
    cols = np.arange(100, 300)
    col = np.repeat(cols, n).astype(np.int32)
    row = np.tile(np.arange(n) * 10.0 + 50.0, cols.size)
    rng = np.random.default_rng(1)
    widths = raster.widths[first : first + n]
    area = (np.tile(widths, cols.size) * 300.0 * rng.lognormal(0.0, 0.03, col.size)).astype(
        np.float32
    )
    number = np.tile(raster.numbers[first : first + n], cols.size)
    result = run_stage(
        CodeWindowNumbering,
        _ordered_truth(col, row, area, number),
        context=StageContext(raster=raster),
    )
    assert np.array_equal(result.number, number)


def test_uneven_albedo_is_not_read_as_code() -> None:
    """Hair: the neighbour ratios scatter far more than the heavy/light step; the component
    is left unnumbered rather than placed by chance."""
    col, row, _area, number = truth_lines(back("normal"))
    numbers = np.unique(number)
    keep = np.isin(number, numbers[10:24])
    rng = np.random.default_rng(5)
    noisy = (100.0 * rng.lognormal(0.0, 0.8, int(keep.sum()))).astype(np.float32)
    result = run_stage(
        CodeWindowNumbering,
        _ordered_truth(col[keep], row[keep], noisy, number[keep]),
        context=_context(),
    )
    assert np.all(result.number == -1)
    assert any(w in result.reason for w in ("reliable", "ambiguous", "explains"))


def test_column_check_refuses_a_pair_two_spacings_apart_numbered_three_apart() -> None:
    from rasterserver_plugins.numbering_checks import column_order_conflicts

    # five columns, lines every 8 px numbered 10, 11, 12, 13 where the third line is not
    # numbered (a line left out); in the last two columns the line below the gap carries a
    # number one too high (a line continued across a depth step of a whole spacing)
    col = np.repeat(np.arange(5), 4).astype(np.int32)
    row = np.tile([100.0, 108.0, 116.0, 124.0], 5)
    number = np.tile([10, 11, -1, 13], 5).astype(np.int32)
    number[[15, 19]] = 14
    clash = column_order_conflicts(col, row, number)
    assert clash.tolist() == [False] * 13 + [True, False, True] + [False, True, False, True]
    # the correct columns stay: two spacings, numbers two apart
    assert not np.any(column_order_conflicts(col[:12], row[:12], number[:12]))


def test_version_is_bumped() -> None:
    assert CodeWindowNumbering.version == "30"
    params = CodeWindowNumbering.Params()
    assert params.bracket_line is True
    assert params.final_order is True
    assert (params.kink_bend, params.kink_ratio) == (0.0, 5.0)
    assert params.linked_one_sided == 50
    assert (params.pair_shift, params.shift_block) == (True, 20)
    assert params.one_sided_peaks == 6
    assert (params.outer_gap, params.meet_tolerance) == (1.2, 1.0)
    assert (params.block_least, params.block_gain, params.block_clean) == (15, 0.3, 0.15)
    assert params.block_ends == 2
    assert (params.reading_run, params.reading_least) == (6, 3)
    assert (params.reading_margin, params.reading_clean) == (0.3, 0.2)
    assert (params.poor_run_factor, params.final_isolated) == (0.0, True)
    assert (params.end_margin, params.end_refused, params.end_dim) == (3, 6, 0.3)
    assert params.group_ties == 3.0
    assert (params.edge_run, params.edge_reach, params.edge_company) == (6, 1.5, 3)
    assert (params.surround_share, params.surround_reach) == (0.4, 8)
    assert (params.surround_length, params.surround_passes) == (80, 3)
    assert (params.skip_ratio, params.skip_line_peaks, params.skip_line_share) == (1.9, 3, 0.2)
    assert (params.detached_peaks, params.detached_brightness) == (100, 1.0)
    assert (params.detached_gap_low, params.detached_gap_high) == (0.6, 1.6)


def test_cloth_pieces_two_levels_off_are_refused_by_their_intensity_ratios() -> None:
    """A waistband whose depth step is two line spacings: in its columns the two lines at
    the step are hidden and the lines below it are taken as the next ones (line sequence
    cannot see the step). The component's code, read over all its columns, is unmoved; the
    pieces' intensity ratios with their column neighbours contradict their numbers, except
    where the code two lines on happens to have the same kinds on both sides of a piece:
    those stay wrong with the pair check alone; the code read in tiles refuses them all."""
    from rasterserver_plugins.line_numbering import number_lines

    col, row, area, number = truth_lines(back("normal"))
    ordered = _ordered_truth(col, row, area, number)
    numbers = np.unique(number)
    cut = numbers[-14]
    cloth = (col >= 200) & (col < 260)
    keep = ~(cloth & np.isin(number, numbers[-16:-14]))  # the two hidden lines
    n_lines = numbers.size
    lid = ordered.line_id.copy()
    piece = cloth & (number >= cut)
    lid[piece] += n_lines  # each cloth piece a line of its own
    line_order = np.concatenate([ordered.line_order, ordered.line_order - 2])
    line_component = np.zeros(2 * n_lines, np.int32)
    sel = np.flatnonzero(keep)
    bad = OrderedLines.extend(
        ordered,
        col=col[sel],
        row=row[sel],
        area=area[sel],
        height=ordered.height[sel],
        width=ordered.width[sel],
        line_id=lid[sel].astype(np.int32),
        order=line_order[lid[sel]].astype(np.int32),
        line_order=line_order.astype(np.int32),
        line_component=line_component,
    )
    truth = np.concatenate([numbers, numbers])
    pieces = np.arange(n_lines, 2 * n_lines)[numbers >= cut]
    raster = rendering_raster()
    naive, _, _ = number_lines(bad, raster, pair_check=False, tile_check=False)
    checked, _, comps = number_lines(bad, raster, tile_check=False)
    tiled, _, tile_comps = number_lines(bad, raster)
    assert np.count_nonzero((naive[pieces] >= 0) & (naive[pieces] != truth[pieces])) >= 8
    assert not np.any((checked >= 0) & (checked != truth) & (np.arange(truth.size) < n_lines))
    naive_wrong = np.count_nonzero((naive[pieces] >= 0) & (naive[pieces] != truth[pieces]))
    wrong = np.count_nonzero((checked[pieces] >= 0) & (checked[pieces] != truth[pieces]))
    assert wrong <= naive_wrong // 2
    assert np.count_nonzero(checked[:n_lines] >= 0) >= n_lines - 3
    assert any("intensity ratio" in c.reason for c in comps)
    # read in their own columns (the code tiles, version 5), the pieces contradict the
    # component's placement as a block: none stays wrong, every whole line keeps its number
    assert not np.any((tiled[pieces] >= 0) & (tiled[pieces] != truth[pieces]))
    assert not np.any((tiled[:n_lines] >= 0) & (tiled[:n_lines] != truth[:n_lines]))
    assert np.count_nonzero(tiled[:n_lines] >= 0) >= n_lines - 1
    assert any("in their own columns" in c.reason for c in tile_comps)


def test_a_whole_back_with_a_block_a_level_off_is_numbered_and_the_block_refused() -> None:
    """Line sequence hid one line across the whole width and put every line below it a
    level up (a cloth below a waistband): the back's best placement stands out by far but
    leaves over a quarter of its differences unexplained. Version 4 refused the whole
    back; version 5 places it, and the block is refused (here by the level windows of
    ``locally_contradicted``, the block spanning every column; the code bands where it
    spans some)."""
    from rasterserver_plugins.line_numbering import number_lines

    col, row, area, number = truth_lines(back("normal"))
    numbers = np.unique(number)
    hidden = numbers[-22]
    keep = number != hidden
    col, row, area, number = col[keep], row[keep], area[keep], number[keep]
    ordered = _ordered_truth(col, row, area, number)
    lines = np.unique(number)
    line_order = np.arange(lines.size, dtype=np.int32)  # consecutive: the hidden line lost
    bad = OrderedLines.extend(
        ordered, line_order=line_order, order=line_order[ordered.line_id].astype(np.int32)
    )
    raster = rendering_raster()
    off, _, comps = number_lines(bad, raster, tile_check=False)
    assert np.all(off == -1)
    assert "explains too little" in comps[0].reason
    numbered, _, comps = number_lines(bad, raster)
    right = numbered == lines
    assert not np.any((numbered >= 0) & ~right)  # nothing wrong
    # most lines above the step keep their numbers (the level windows and the bands refuse
    # a few next to the block)
    assert np.count_nonzero(right[lines < hidden]) >= 0.75 * np.count_nonzero(lines < hidden)
    assert np.count_nonzero(numbered[lines > hidden] >= 0) == 0
    assert comps[0].offset >= 0 and comps[0].reason == ""


def _real_bodies():  # type: ignore[no-untyped-def]
    """The clinic-scene benchmark (``benchmarks/real_bodies.py``) as a module: its scenes
    and its scoring against the simulator's per-pixel line numbers."""
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "real_bodies.py"
    spec = importlib.util.spec_from_file_location("real_bodies_for_tests", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_line_ends_crossing_a_cloth_side_edge_are_refused() -> None:
    """Clinic scene 7285 (window-7 m-sequence, hands on hips, waistband): at the flank,
    lines of the back continue across the cloth's edge onto the cloth's next line, a level
    off, with no gap to show it. Version 5 numbered 16 such peaks wrongly; version 6 refuses
    the peaks beside the refused block and the stranded line ends, and keeps the back."""
    bench = _real_bodies()
    frame = bench.render_scene(7285)
    v5 = {"block_edge_check": False, "min_run": 0, "island_peaks": 0, **STEPS_13_21_OFF}
    # judged with peaks version 4, under which the case was found (with version 5's peaks,
    # the flanked ones kept, version 5 of the numbering errs on 4 peaks here)
    bench._init(None, {"numbers": v5, "peaks": PEAKS_4})
    before = bench.score_frame(frame)
    bench._init(None, {"peaks": PEAKS_4})
    after = bench.score_frame(frame)
    bench._init(None, None)
    assert bench.score_frame(frame)["wrong_peaks"] == 0  # the installed chain
    # 16 wrong peaks with version 5 on AMD EPYC, 6 on an Intel Xeon: the rendering's last
    # bits differ between processors, and which line ends land on the next line with them
    assert before["wrong_peaks"] >= 5 and before["wrong_objects"] == ["clothing"]
    assert after["wrong_peaks"] == 0
    assert after["back_covered"] >= 0.97 * after["back_crossings"]
    assert after["back_covered"] >= before["back_covered"] - 0.01 * before["back_crossings"]


@pytest.mark.slow
def test_a_clinic_scene_where_version_6_errs_is_refused_by_version_7() -> None:
    """Clinic scenes 7325, 7401, 7037 and 7428 of ``benchmarks/real_bodies.py`` (window-7
    m-sequence, arms close, waistband): with version 6's block-edge check (only the code's
    refusals doubtful, refused wherever they touch) peaks at the cloth's edge carry their
    line's number onto the cloth's next line; version 7 refuses every one of them, and in
    at least one scene errs nowhere and numbers more of the back.
    The rendering's last bits differ between processors, and with them which line ends land
    on the next line: version 6 errs in 7325 on AMD EPYC, in 7401 on an Intel Xeon before
    the peaks' version 4; since then in 7037 and 7428 (4 and 6 peaks) on an Intel Xeon, in
    7325 and 7428 on an AMD EPYC (where version 7 errs on one other peak of 7428)."""
    from rasterserver.simulator.body import clinic_station

    bench = _real_bodies()  # its scenes: the benchmark's light, noise and blur
    cleared = 0
    for seed in (7325, 7401, 7037, 7428):
        rendering = bench.render_scene(seed)
        station = clinic_station(seed, rendering.code)
        context = StageContext(calibration=station, raster=station.raster_definition)
        peaks = run_stage(FirstMomentPeaks, Image(rendering.image), params=PEAKS_5)
        ordered = run_stage(HierarchicalLineOrder, run_stage(HierarchicalLineSearch, peaks))
        truth, _ = truth_of_peaks(ordered.col, ordered.row, rendering.line_rows)
        h = rendering.line_number.shape[0]
        rows = np.clip(np.rint(ordered.row).astype(int), 0, h - 1)
        truth = np.where(rendering.line_number[rows, ordered.col] == truth, truth, -1)

        # the later versions' steps off: brackets (8), line ends (10), groups (11), frame
        # edges (12), ends among unnumbered peaks (13)
        v7 = {"bracket_run": 0, "end_margin": 0, "end_dim": 0.0, "group_ties": 0, "edge_run": 0}
        v7.update(STEPS_13_21_OFF)
        v6 = {"doubtful": "code", "block_share": 0.0, "island_peaks": 0, **v7}
        wrong, right = [], []
        for params in (v6, v7):
            out = run_stage(CodeWindowNumbering, ordered, params=params, context=context)
            known = (out.number >= 0) & (truth >= 0)
            wrong.append(known & (out.number != truth))
            right.append(int(np.sum(known & (out.number == truth))))
        reason = out.reason
        # no peak that version 6 numbers wrongly keeps its wrong number in version 7 (on an
        # AMD EPYC, 7428's version 7 errs on another peak, one that version 6 left
        # unnumbered, and numbers less of the back there)
        assert not np.any(wrong[0] & wrong[1]), seed
        if np.any(wrong[0]) and not np.any(wrong[1]):
            cleared += 1
            assert right[1] > right[0]
            assert "directly beside a doubtful line" in reason
    assert cleared >= 1


@pytest.mark.slow
def test_a_clinic_scene_numbers_more_of_its_back_with_bracketed_peaks() -> None:
    """Clinic scene 7044 of ``benchmarks/real_bodies.py`` (default code, dark hair): lines
    of the upper back broken into fragments by the hair stay unnumbered in version 7;
    version 8 numbers those its columns settle, and numbers none wrongly."""
    bench = _real_bodies()
    frame = bench.render_scene(7044)
    v7 = {"bracket_run": 0, "group_ties": 0, "edge_run": 0, **STEPS_13_21_OFF}
    bench._init(None, {"numbers": v7})
    before = bench.score_frame(frame)
    bench._init(None, None)
    after = bench.score_frame(frame)
    assert before["wrong_peaks"] == 0 and after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] + 0.01 * before["back_crossings"]


@pytest.mark.slow
def test_clinic_scenes_where_version_9_errs_at_line_ends_are_refused_by_version_10() -> None:
    """Clinic scenes 7409 (window-7 m-sequence, arms close: the last peak of arm lines lies
    on the cloth behind, the next raster line, dim) and 7167 (45:55 code, hands on hips:
    back lines carried across the cloth's side edge onto its next line beyond their
    refused peaks). Version 9 numbered them wrongly (on AMD EPYC: 3 and 3 peaks); version
    10 refuses the dim end peaks and the three peaks beyond six refused ones, and keeps
    the back."""
    v9 = {"end_margin": 0, "end_dim": 0.0, "group_ties": 0, "edge_run": 0, **STEPS_13_21_OFF}
    _assert_refused_where_earlier_erred((7409, 7167), v9, max_loss=0.01)


#: Clinic scenes kept as rendered (``benchmarks/real_bodies.py --cache tests/data/scenes``,
#: 2026-11-29, Intel Xeon with AVX-512). The renderer is deterministic on one machine, but
#: its frames differ in their last bits between processors, and a rare error shown by a
#: scene rendered on one (AMD EPYC, where the tests of versions 18 and 19 were first
#: written) may not show on another: a test that must see an earlier version err reads
#: the frame it was written on.
SCENES = Path(__file__).resolve().parents[1] / "data" / "scenes"


def _scene(bench, seed: int, raster: str | None, stored: bool):  # type: ignore[no-untyped-def]
    """Clinic scene ``seed`` (through ``raster``): rendered, or read from ``SCENES``."""
    if not stored:
        return bench.render_scene(seed, raster)
    name = f"scene-{seed}-{raster}.npz" if raster else f"scene-{seed}.npz"
    return bench.Frame.load(SCENES / name)


def _kept_scene_scores(seed: int, before: dict, after: dict | None = None) -> tuple[dict, dict]:
    """Kept clinic scene ``seed`` scored with the stage parameters ``before`` and ``after``
    (``{"numbers": ...}``; None: the installed chain's)."""
    bench = _real_bodies()
    frame = _scene(bench, seed, None, stored=True)
    scores = []
    for params in (before, after):
        bench._init(None, params)
        scores.append(bench.score_frame(frame))
    return scores[0], scores[1]


def _assert_refused_where_earlier_erred(
    seeds: tuple[int, ...],
    earlier: dict,
    max_loss: float,
    raster: str | None = None,
    stored: bool = False,
) -> None:
    """The clinic scenes ``seeds`` (seen through ``raster``, a built-in raster's name,
    instead of the seed's code; ``stored``: the frames kept in ``SCENES``) scored with the
    ``earlier`` version's numbering parameters and with this one's, both on the line order
    of version 1 (``ORDER_1``): at least one erred before, none errs now, and none loses
    more than ``max_loss`` of its back's crossings; nor does the installed chain err."""
    bench = _real_bodies()
    erring = 0
    for seed in seeds:
        frame = _scene(bench, seed, raster, stored)
        bench._init(None, _on_peaks_5({"numbers": earlier, "order": ORDER_1}))
        before = bench.score_frame(frame)
        bench._init(None, _on_peaks_5({"order": ORDER_1}))
        after = bench.score_frame(frame)
        erring += before["wrong_peaks"] > 0
        assert after["wrong_peaks"] == 0
        assert after["back_covered"] >= before["back_covered"] - max_loss * before["back_crossings"]
        bench._init(None, None)
        assert bench.score_frame(frame)["wrong_peaks"] == 0
    assert erring >= 1


@pytest.mark.slow
def test_a_clinic_scene_numbers_the_line_pieces_under_hair_as_a_group() -> None:
    """Clinic scene 7193 of ``benchmarks/real_bodies.py`` (window-7 m-sequence, hands on
    hips, dark hair over the upper back): the hair's strands cut the back's lines into
    dashes, hundreds of components of one to ten lines that touch the numbered trunk over
    a few columns each. Version 10 left them unnumbered (about 6 % of the back); version
    11 groups the pieces whose contacts agree and numbers the group from its contacts with
    the trunk, with no wrong peak."""
    bench = _real_bodies()
    frame = bench.render_scene(7193)
    bench._init(None, {"numbers": {"group_ties": 0, "edge_run": 0, **STEPS_13_21_OFF}})
    before = bench.score_frame(frame)
    bench._init(None, None)
    after = bench.score_frame(frame)
    assert before["wrong_peaks"] == 0 and after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] + 0.03 * before["back_crossings"]
    assert after["back_covered"] >= 0.97 * after["back_crossings"]
    # the pieces no group placed are counted together in the reason, not listed one by one
    from rasterserver.simulator.body import clinic_station

    station = clinic_station(7193, frame.code)
    context = StageContext(calibration=station, raster=station.raster_definition)
    peaks = run_stage(FirstMomentPeaks, Image(frame.image))
    ordered = run_stage(HierarchicalLineOrder, run_stage(HierarchicalLineSearch, peaks))
    reason = run_stage(CodeWindowNumbering, ordered, context=context).reason
    assert "component(s) with too few lines to read the code" in reason
    assert "grouped" not in reason and len(reason) < 3000


@pytest.mark.slow
def test_clinic_scenes_where_version_11_errs_at_the_frames_edge_are_refused_by_version_12() -> None:
    """Clinic scenes 7166 and 7250 (light:heavy 1:2, waistband) and 7404 (default code):
    back lines run down into the frame's bottom edge and, in their last columns, onto the
    cloth below the waistband, which shows the next raster line at the same row; the
    frame's edge cuts the cloth to pieces too short to read. Version 11 numbered those ends
    wrongly (on an Intel Xeon: 5, 6 and 9 peaks); version 12 refuses them and keeps the
    back."""
    v11 = {"edge_run": 0, **STEPS_13_21_OFF}
    _assert_refused_where_earlier_erred((7166, 7250, 7404), v11, max_loss=0.005)


@pytest.mark.slow
def test_clinic_scenes_where_version_12_errs_at_a_cloths_side_edge_are_refused_by_13() -> None:
    """Clinic scenes 7829 and 9089 (window-7 m-sequence, waistband): at the back's lower
    corners, lines cross the cloth's side edge with no gap, step or change of height and
    carry their numbers onto the cloth's next lines, whose own lines are refused. Version 12
    numbered them wrongly (on AMD EPYC: 32 peaks over 4 lines, 7 peaks over 3); version 13
    refuses the long lines' ends lying among unnumbered peaks, and keeps the back."""
    v12 = dict(STEPS_13_21_OFF)
    _assert_refused_where_earlier_erred((7829, 9089), v12, max_loss=0.01)


@pytest.mark.slow
def test_clinic_scenes_where_version_13_numbers_across_a_skipped_line_are_refused() -> None:
    """Clinic scenes 7099 and 7224 seen through the held-out raster's tuning twin (window-8
    m-sequence, light:heavy 35:65, waistband): the dark cloth shows the heavy lines only,
    so two of its lines were ordered as neighbours and numbered as such (7099 on an Intel
    Xeon: lines 123 and 125 numbered 121 and 122, 69 peaks; 7224 on AMD EPYC: 14 peaks).
    They lie two spacings apart where the lines above them in their columns lie one apart;
    version 14 refuses them (the rendered frames differ by processor: on AMD EPYC version
    14 leaves 10 of 7224's peaks, which version 15 refuses as detached), and keeps the
    back."""
    _assert_refused_where_earlier_erred(
        (7099, 7224),
        {"skip_ratio": 0.0, "detached_peaks": 0, **V17},
        max_loss=0.005,
        raster="mseq8b-35to65",
    )


@pytest.mark.slow
def test_clinic_scenes_where_version_14_numbers_detached_pieces_are_refused_by_15() -> None:
    """Clinic scenes 7343 and 7585 through the tuning twin (window-8 m-sequence, 35:65):
    in 7343 a block of short lines at the frame's top, in 7585 the cloth's lines just below
    a waistband (a brightness step of 4-7 times and 1.4 spacings in depth), numbered with
    the back's component two and one lines off (on AMD EPYC: 70 peaks each). The checks had
    refused the peaks where they touch the back; no contact left joins them to it. Version
    15 refuses them, and keeps the back."""
    _assert_refused_where_earlier_erred(
        (7343, 7585), {"detached_peaks": 0, **V17}, max_loss=0.005, raster="mseq8b-35to65"
    )


@pytest.mark.slow
def test_clinic_scenes_through_a_faint_code_number_more_of_their_backs() -> None:
    """Clinic scenes 7707 and 7879 through the 45:55 code (its kinds differ by a log area
    ratio of 0.2): version 15 refused the back's peaks beside small pieces the code cannot
    read, as if they were a refused block, and lines whose ratio with a neighbour departed
    from the code's by 0.75 of a kind's difference, within the ratios' scatter. Version 16
    takes only the code's own refusals as doubtful for a faint code, version 17 needs a
    ratio of the other sign to refuse a pair. Version 17 numbers more of the back than
    either, and none wrongly (on AMD EPYC 7707: 89.4 -> 91.4 -> 94.2 % of its back; 7879
    loses 0.2 point with version 16 and gains with 17)."""
    bench = _real_bodies()
    gains = []
    for seed in (7707, 7879):
        frame = bench.render_scene(seed)
        assert frame.code == "w9-45to55"
        covered = []
        v17 = dict(V17)
        variants = ({"faint_ratio": 1.0, **v17}, {"faint_departure": 0.75, **v17}, v17, V20, None)
        for params in variants:
            bench._init(None, {"numbers": params} if params else None)
            scored = bench.score_frame(frame)
            covered.append(scored["back_covered"] / scored["back_crossings"])
            if params is v17 or params is V20 or params is None:
                # the frames differ by processor: the earlier versions' errors may too
                assert scored["wrong_peaks"] == 0
        assert covered[2] > max(covered[:2])
        # version 18 refuses fewer of the code's runs and, last, the peaks left alone in
        # their column (a few hundredths of a point); 19 and 20 refuse nothing here
        assert covered[3] >= covered[2] - 0.002
        # version 21 refuses the short lines no column confirms from both sides: the faint
        # code's hair and shoulder dashes (on AMD EPYC 7707 loses 0.26 point, 7879 0.01)
        assert covered[4] >= covered[3] - 0.004
        gains.append(covered[2] - covered[0])
    assert min(gains) > 0.01 and max(gains) > 0.03


def _notes_of_clinic_scene(
    seed: int, raster: str | None = None, order: dict | None = None
) -> list[str]:
    """The notes of the numbering's reason on clinic scene ``seed`` (seen through
    ``raster`` instead of the seed's code; ``order``: the line order's parameters)."""
    from rasterserver.simulator.body import clinic_station

    frame = _real_bodies().render_scene(seed, raster)
    station = clinic_station(seed, frame.code)
    context = StageContext(calibration=station, raster=station.raster_definition)
    peaks = run_stage(FirstMomentPeaks, Image(frame.image), params=PEAKS_5)
    lines = run_stage(HierarchicalLineSearch, peaks)
    ordered = run_stage(HierarchicalLineOrder, lines, params=order)
    return run_stage(CodeWindowNumbering, ordered, context=context).reason.split("; ")


@pytest.mark.slow
def test_a_clinic_scene_reports_the_ends_among_unnumbered_peaks() -> None:
    """The numbering's reason counts the peaks the new step refuses, for the overlay."""
    note = [n for n in _notes_of_clinic_scene(7829) if "lying among unnumbered peaks" in n]
    assert len(note) == 1 and int(note[0].split()[0]) > 0


@pytest.mark.slow
@pytest.mark.parametrize(
    ("seeds", "words"),
    [
        ((7099, 7224), "two line spacings apart in their column"),
        ((7343,), "frame's main numbered block"),
    ],
)
def test_clinic_scenes_report_the_peaks_the_last_steps_refuse(
    seeds: tuple[int, ...], words: str
) -> None:
    """The numbering's reason counts the peaks versions 14's and 15's steps refuse, for the
    overlay (on one of the scenes at least: the frames differ by processor), on the line
    order of version 1, under which they were found."""
    notes = [n for seed in seeds for n in _notes_of_clinic_scene(seed, "mseq8b-35to65", ORDER_1)]
    note = [n for n in notes if words in n]
    assert note and all(int(n.split()[0]) > 0 for n in note)


@pytest.mark.slow
def test_clinic_scenes_where_a_line_end_loses_its_column_neighbours_are_refused_last() -> None:
    """Clinic scene 7378 through the twin raster (window-8 m-sequence, 35:65; the frame
    kept in ``SCENES``): line ends cross onto the cloth's next lines with no step (the
    cloth stands off by one line's depth there). Their column neighbours were numbered when
    the peak checks judged them, and the last steps (line ends, long lines' ends among
    unnumbered peaks) refused them, leaving the peaks numbered by their lines' continuity
    alone (version 17: 4 peaks one line off; on AMD EPYC the rendered scenes 7632 and 34069
    showed the same). Version 18 judges such peaks again last (``final_isolated``), and
    keeps the back."""
    earlier = {"final_isolated": False, **V18}
    _assert_refused_where_earlier_erred((7378,), earlier, 0.002, "mseq8b-35to65", stored=True)


@pytest.mark.slow
def test_clinic_scenes_where_a_line_end_runs_onto_a_cloth_read_a_line_off_are_refused() -> None:
    """Clinic scenes 7038 and 7408 through the twin raster (window-8 m-sequence, 35:65; the
    frames kept in ``SCENES``), waistband: lines' ends run onto the cloth, whose surface
    shows the next raster line at their rows (version 18: 3 peaks each numbered a line
    low; on AMD EPYC the rendered scenes 7805 and 8154 showed the same). The cloth's lines
    beyond them in their columns were refused, yet their brightness ratios, read on down
    the column from the ends' peaks, follow the code a line on. Version 19 refuses those
    peaks (``reading_run``), and keeps the backs. What each scene keeps wrong is another
    case: a short cloth piece whose column beyond is not read (7038: 3 peaks), an arm's
    line ends crossing onto the cloth (7408: 2). Judged with peaks version 4, under which
    the case was found; with version 5's peaks (the flanked ones kept) version 18 reads
    them right, and the installed chain errs no more than it did. Judged with line search
    version 2 and line order version 1: version 3 of the line search (turn and vertex cuts)
    ends some of those lines before the cloth."""
    bench = _real_bodies()
    for seed, left in ((7038, 3), (7408, 2)):
        frame = _scene(bench, seed, "mseq8b-35to65", stored=True)
        earlier = {"peaks": PEAKS_4, "lines": LINES_2, "order": ORDER_1}
        bench._init(None, {"numbers": V18, **earlier})
        before = bench.score_frame(frame)
        bench._init(None, earlier)
        after = bench.score_frame(frame)
        assert after["wrong_peaks"] <= left and before["wrong_peaks"] >= after["wrong_peaks"] + 3
        assert after["back_covered"] >= before["back_covered"] - 0.002 * before["back_crossings"]
        bench._init(None, None)
        assert bench.score_frame(frame)["wrong_peaks"] <= left


@pytest.mark.slow
def test_a_clinic_scene_whose_lines_run_on_onto_a_cloth_is_refused_as_a_block() -> None:
    """Clinic scene 7632 (the default code, waistband; the frame kept in ``SCENES``): at the
    right flank the back's lines run on smoothly onto the cloth, which stands off by about
    a line's depth and shows the next raster line at their rows; version 19 numbers 42
    peaks there one line low, and no unnumbered peak is left beyond them to read. The
    cloth's own column ratios read the code a line on: version 20 refuses the block
    (``block_least``), and the line-end steps take what it leaves. One wrong peak is left,
    a single line end on the other flank (another case); the back keeps all but 0.2 %."""
    bench = _real_bodies()
    frame = _scene(bench, 7632, None, stored=True)
    bench._init(None, _on_peaks_5({"numbers": V19}))
    before = bench.score_frame(frame)
    bench._init(None, _on_peaks_5({"numbers": V20}))
    after = bench.score_frame(frame)
    assert before["wrong_peaks"] >= 40 and before["wrong_objects"] == ["clothing"]
    assert after["wrong_peaks"] <= 1
    assert after["back_covered"] >= before["back_covered"] - 0.002 * before["back_crossings"]
    # version 21 (short one-sided lines) keeps it so, for a few peaks of the back
    bench._init(None, None)
    installed = bench.score_frame(frame)
    assert installed["wrong_peaks"] <= 1
    assert installed["back_covered"] >= after["back_covered"] - 0.001 * after["back_crossings"]


@pytest.mark.slow
def test_a_clinic_scene_whose_short_cloth_line_rests_on_one_neighbour_is_refused() -> None:
    """Clinic scene 7770 (the ``w8-1to2`` code, waistband; the frame kept in ``SCENES``):
    below the back's line 101 a 4-peak line of the cloth, which stands off by about a line's
    depth, shows line 103 where the back's order puts 102; its column neighbour below is
    unnumbered. Version 20 numbers it 102 from that one contact; version 21 refuses the
    short line no column confirms from both sides (``one_sided_peaks``), and the back loses
    nothing. Judged with peaks version 4, under which the case was found; with version 5's
    peaks (the flanked ones kept) version 20 numbers the line right, and the installed chain
    errs nowhere either. The cloth line's contact with the back's line 101 is an overlap
    by the ends of the two (a staircase along the cloth's edge): with the line order's
    staircase option, which does not count it, version 20 does not err there either.
    Judged on line order version 1; on version 3 version 20 does not err there."""
    bench = _real_bodies()
    frame = _scene(bench, 7770, None, stored=True)
    bench._init(None, {"numbers": V20, "peaks": PEAKS_4, "order": ORDER_1})
    before = bench.score_frame(frame)
    bench._init(None, {"peaks": PEAKS_4, "order": ORDER_1})
    after = bench.score_frame(frame)
    assert before["wrong_peaks"] == 4 and before["wrong_objects"] == ["clothing"]
    assert after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] - 0.001 * before["back_crossings"]
    bench._init(None, {"numbers": V20, "peaks": PEAKS_4, "order": {**STAIRCASE, **ORDER_1}})
    assert bench.score_frame(frame)["wrong_peaks"] == 0
    bench._init(None, None)
    assert bench.score_frame(frame)["wrong_peaks"] == 0


@pytest.mark.slow
def test_a_cloth_block_placed_a_line_off_behind_an_albedo_edge_is_refused() -> None:
    """Scene 7728 through the twin raster (window-8 m-sequence, 35:65; the frame kept in
    ``SCENES``, rendered on an AMD EPYC): at the right flank four short lines of the cloth
    below a waistband are numbered one line low. The pair of the first two contradicts the
    code (the first should be light) but would agree were both one more; version 21 spares
    the shorter line for its agreeing pairs below, which are all heavy and agree at either
    placement, and 34 peaks err. Version 22 counts only pairs that tell the placements
    apart (``pair_shift``) and refuses the block tied by the others (``shift_block``).
    Judged on line order version 1, under which the case was found."""
    bench = _real_bodies()
    frame = _scene(bench, 7728, "mseq8b-35to65", stored=True)
    bench._init(None, _on_peaks_5({"numbers": V21, "order": ORDER_1}))
    before = bench.score_frame(frame)
    bench._init(None, _on_peaks_5({"numbers": {"shift_block": 0, **V22}, "order": ORDER_1}))
    support_only = bench.score_frame(frame)
    bench._init(None, _on_peaks_5({"order": ORDER_1}))
    after = bench.score_frame(frame)
    assert before["wrong_peaks"] >= 30 and before["wrong_objects"] == ["clothing"]
    assert support_only["wrong_peaks"] < before["wrong_peaks"] / 2
    assert after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] - 0.001 * before["back_crossings"]
    bench._init(None, None)
    assert bench.score_frame(frame)["wrong_peaks"] == 0


@pytest.mark.slow
def test_a_cloth_piece_numbered_from_the_skin_above_it_alone_is_refused() -> None:
    """Scene 44157 through the twin raster (window-8 m-sequence, 35:65; the frame kept in
    ``SCENES``, rendered on an AMD EPYC): at the left corner of a waistband three short
    cloth lines form a component the code cannot place; it inherits its numbers from the
    skin's lines it touches above the waistband, which hides a line (the cloth stands off
    by a line's depth): 22 peaks one line low in version 22. Nothing numbered touches it
    from below (the cloth's other lines are refused). Version 23 refuses small inherited
    components touched from one side only (``linked_one_sided``), and keeps the back.
    Judged on line order version 1, under which the case was found."""
    bench = _real_bodies()
    frame = _scene(bench, 44157, "mseq8b-35to65", stored=True)
    bench._init(None, _on_peaks_5({"numbers": V22, "order": ORDER_1}))
    before = bench.score_frame(frame)
    bench._init(None, _on_peaks_5({"order": ORDER_1}))
    after = bench.score_frame(frame)
    assert before["wrong_peaks"] >= 20 and before["wrong_objects"] == ["clothing"]
    assert after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] - 0.001 * before["back_crossings"]
    bench._init(None, None)
    assert bench.score_frame(frame)["wrong_peaks"] == 0
    reason = bench.run_stages(frame, _on_peaks_5({"order": ORDER_1}))[0].reason
    notes = [n for n in reason.split("; ") if "touching them on one side only" in n]
    assert len(notes) == 1 and int(notes[0].split()[0]) >= 20


@pytest.mark.slow
def test_the_kinked_ends_option_refuses_a_line_linked_onto_an_arms_line() -> None:
    """Tuning scenes 7604 through the twin raster (hands on hips) and 48717 (window-7
    m-sequence, hands on hips), frames kept in ``SCENES`` (rendered on an AMD EPYC): where
    the arm's edge cuts the back's lines, the line search linked a back line's first peak
    to the arm's line two numbers off (a bend of 1.6 and 2.4 px off the line's course),
    while the back's lines either side begin one column later. Version 23 numbers that
    peak wrongly in each; the kinked-ends option (``kink_bend`` 0.8, tried as version 24
    and not adopted: it caught none of the held-out frames' wrong peaks) refuses it and
    keeps the back. Judged with line search version 2; with version 3's lines (turn and
    vertex cuts) the installed chain errs in neither scene."""
    bench = _real_bodies()
    for seed, raster in ((7604, "mseq8b-35to65"), (48717, None)):
        frame = _scene(bench, seed, raster, stored=True)
        bench._init(None, _on_peaks_5({"lines": LINES_2}))
        installed = bench.score_frame(frame)
        bench._init(None, _on_peaks_5({"numbers": KINKED, "lines": LINES_2}))
        kinked = bench.score_frame(frame)
        bench._init(None, None)
        assert installed["wrong_peaks"] == 1 and kinked["wrong_peaks"] == 0
        lost = installed["back_covered"] - kinked["back_covered"]
        assert lost <= 0.001 * installed["back_crossings"]
        assert bench.score_frame(frame)["wrong_peaks"] == 0
    reason = bench.run_stages(
        _scene(bench, 48717, None, stored=True),
        _on_peaks_5({"numbers": KINKED, "lines": LINES_2}),
    )[0]
    assert "bends off the line's course where the lines numbered either side end" in reason.reason


@pytest.mark.slow
def test_numbers_out_of_order_down_a_column_are_refused() -> None:
    """Tuning scene 77221 (window-7 m-sequence, arms close; the frame kept in ``SCENES``,
    rendered on an AMD EPYC): at a waistband's edge the line search carried the cloth's
    line 107 onto the start of a line numbered 105, below a cloth peak numbered 105 in the
    same column. Version 23 leaves that peak numbered wrongly; version 25 refuses both
    peaks of a column pair whose numbers do not increase downwards, and keeps the back.
    Judged with line search version 2 (and version 25 against 23: version 29 refuses the
    peak by its line-end steps too); with version 3's lines (turn and vertex cuts) even
    version 23 does not err there, and the installed chain errs nowhere either."""
    bench = _real_bodies()
    frame = _scene(bench, 77221, None, stored=True)
    bench._init(None, {"numbers": V23, "lines": LINES_2})
    before = bench.score_frame(frame)
    bench._init(None, {"numbers": V25, "lines": LINES_2})
    after = bench.score_frame(frame)
    assert before["wrong_peaks"] == 1 and before["wrong_objects"] == ["clothing"]
    assert after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] - 0.001 * before["back_crossings"]
    reason = bench.run_stages(frame, {"numbers": V25, "lines": LINES_2})[0].reason
    assert "whose numbers do not increase down their column" in reason
    bench._init(None, None)
    assert bench.score_frame(frame)["wrong_peaks"] == 0


@pytest.mark.slow
def test_line_ends_run_onto_another_surface_are_cut_by_the_line_search() -> None:
    """Clinic scenes 62875 (``w9-45to55``, waistband) and 63677 (the default code, an arm;
    frames kept in ``SCENES``, rendered on an Intel Xeon): where two surfaces' lines meet,
    line search version 2 chained one into the other and the numbering carried the line's
    number onto the other surface. In 62875 the corner is rounded by the peaks at the
    contour (row steps 0.55, 0.75, -1.61, -1.09: no link departs by 1.5 px from the steps
    beside it) and two cloth peaks are numbered one line low; version 3's turn cut ends
    the line there. In 63677 the corner is cut, but the peak at its vertex stays with the
    trunk's line onto the arm; version 3's vertex cut leaves it in neither line. Each
    cut alone mends its scene; the back keeps all but 0.19 % (62875: 26 of its 13,955
    crossings lost to the new cuts) and 0.04 % (63677). Judged on line order version 1 and
    numbering version 25 (version 29's line-end steps refuse 63677's end anyway)."""
    bench = _real_bodies()
    for seed, alone, objects in (
        (62875, {"vertex": False}, ["clothing"]),
        (63677, {"turn": None}, ["right-arm"]),
    ):
        frame = _scene(bench, seed, None, stored=True)
        on_25 = {"order": ORDER_1, "numbers": V25}
        bench._init(None, _on_peaks_5({"lines": LINES_2, **on_25}))
        before = bench.score_frame(frame)
        bench._init(None, _on_peaks_5({"lines": alone, **on_25}))
        one_cut = bench.score_frame(frame)
        bench._init(None, _on_peaks_5(on_25))
        after = bench.score_frame(frame)
        assert before["wrong_peaks"] >= 1 and before["wrong_objects"] == objects
        assert one_cut["wrong_peaks"] == 0 and after["wrong_peaks"] == 0
        assert after["back_covered"] >= before["back_covered"] - 0.002 * before["back_crossings"]
        bench._init(None, None)
        assert bench.score_frame(frame)["wrong_peaks"] == 0


@pytest.mark.slow
def test_a_block_ordered_across_a_hidden_line_is_numbered_with_line_order_version_3() -> None:
    """Clinic scene 64298 (the ``w8-1to2`` code; the frame kept in ``SCENES``, rendered on an
    AMD EPYC): line order version 1 takes two lines 1.3-1.6 spacings apart in their columns
    for neighbours, where a line between them is hidden, and orders a block of lines a
    level off; the numbering's code bands see the block's own code contradict its placement
    and refuse it (26 lines), so that 4 % of the back goes unnumbered. Version 3 counts a
    pair only within 1.3 times the gaps beside it: the block is ordered right and numbered,
    with no wrong peak either way."""
    bench = _real_bodies()
    frame = _scene(bench, 64298, None, stored=True)
    bench._init(None, {"order": ORDER_1})
    before = bench.score_frame(frame)
    bench._init(None, None)
    after = bench.score_frame(frame)
    assert before["wrong_peaks"] == 0 and after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] + 0.03 * before["back_crossings"]
    notes = bench.run_stages(frame, {"order": ORDER_1})[0].reason.split("; ")
    refused = [n for n in notes if "a block ordered a level off" in n]
    assert refused and int(refused[0].split()[0]) >= 20
    installed = bench.run_stages(frame)[0].reason
    assert not any("a block ordered a level off" in n for n in installed.split("; "))


#: The line-end steps of version 29 (BENCHMARKS.md "Real bodies" (44)), each with its value.
V29_ENDS = {"outer_gap": 1.2, "one_sided_peaks": 6, "meet_tolerance": 1.0}


@pytest.mark.slow
def test_line_ends_on_another_surface_are_refused_by_version_29() -> None:
    """Tuning scenes of section (44) (frames kept in ``SCENES``, rendered on an AMD EPYC,
    peaks version 6): version 25 numbers peaks wrongly on an arm at a line's end, and
    version 29 refuses them, each by one of its steps alone as well, the back keeping its
    coverage to a thousandth. 210874 (``w8-1to2``, arms away): a trunk line's first two
    peaks, its column's top, lie on the arm raised a line's depth in front, 1.4 times
    farther from the next line than the line further in (``outer_gap``); 210840 (the default
    code, arms away): a 6-peak arm line above the trunk's top line, numbered by that one
    neighbour's contact (``one_sided_peaks`` 6); 210624 (the default code, hands on the
    hips): a trunk line's last peak on the course of the arm's line beginning in the next
    column (``meet_tolerance``)."""
    for seed, wrong, objects, step in (
        (210874, 2, ["left-arm"], "outer_gap"),
        (210840, 4, ["left-arm"], "one_sided_peaks"),
        (210624, 1, ["right-arm"], "meet_tolerance"),
    ):
        before, after = _kept_scene_scores(seed, {"numbers": V25})
        assert before["wrong_peaks"] == wrong and before["wrong_objects"] == objects
        assert after["wrong_peaks"] == 0
        assert after["back_covered"] >= before["back_covered"] - 0.001 * before["back_crossings"]
        _, alone = _kept_scene_scores(
            seed, {"numbers": V25}, {"numbers": {**V25, step: V29_ENDS[step]}}
        )
        assert alone["wrong_peaks"] == 0


@pytest.mark.slow
def test_a_bracketed_run_counted_across_a_hidden_line_is_refused_by_version_30() -> None:
    """Tuning scene 212733 of section (45) (``mseq7``, arms close; the frame kept in
    ``SCENES``, rendered on an AMD EPYC): below the right arm, which hides line 56 in column
    486, version 29's bracket fill numbers the column's unnumbered run between the arm's 55
    and a 60 below by counting the spacings, and a spurious peak in the run makes the count
    add up: two peaks on the back proper get 56 and 57, where their own lines are numbered
    57 and 58 further along. Version 30 leaves a run unnumbered when its peaks' lines carry
    other numbers (``bracket_line``); the back keeps its coverage to two thousandths."""
    before, after = _kept_scene_scores(212733, {"numbers": V29})
    assert before["wrong_peaks"] == 2 and before["wrong_on_back"] == 2
    assert before["wrong_objects"] == ["trunk"]
    _, candidate = _kept_scene_scores(212733, {"numbers": V29}, {"numbers": {"bracket_line": True}})
    for scores in (after, candidate):
        assert scores["wrong_peaks"] == 0
        assert scores["back_covered"] >= before["back_covered"] - 0.002 * before["back_crossings"]


@pytest.mark.slow
def test_a_short_line_numbered_across_an_ambiguous_gap_is_refused_with_the_option() -> None:
    """Tuning scene 213079 seen through the held-out raster (``mseq8-35to65``, arms close;
    the frame kept in ``SCENES``, rendered on an AMD EPYC): a cloth line below a waistband
    is numbered 130 in nine columns from the skin's 129 1.5 line spacings above it (and from
    128 2.5 spacings above), where it is 131. The option ``gap_peaks`` (off; BENCHMARKS.md
    "Real bodies" (45)) refuses a short line numbered across gaps no whole count of spacings
    explains: the nine peaks, and the back keeps its coverage to a thousandth."""
    bench = _real_bodies()
    frame = _scene(bench, 213079, "mseq8-35to65", stored=True)
    bench._init(None, None)
    before = bench.score_frame(frame)
    bench._init(None, {"numbers": {"gap_peaks": 20}})
    after = bench.score_frame(frame)
    bench._init(None, None)
    assert before["wrong_peaks"] == 9 and before["wrong_objects"] == ["clothing"]
    assert after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] - 0.001 * before["back_crossings"]
    assert before["numbered_peaks"] - after["numbered_peaks"] < 30


#: The line-end options tried as version 26 (not adopted: BENCHMARKS.md "Real bodies" (39)).
V26_ENDS = {"meet_tolerance": 1.0, "end_jump": 2.8}


@pytest.mark.slow
def test_line_ends_where_two_surfaces_meet_are_refused_with_the_options() -> None:
    """Clinic scenes 66703 (``w9-45to55``, hands on the hips) and 65930 (``w8-1to2``, a
    waistband; frames kept in ``SCENES``, rendered on an Intel Xeon): the installed
    numbering (version 25) on peaks version 5 numbers one peak wrongly in each, at a line's
    end where two surfaces meet. In 66703 a trunk line starts with a peak on the arm that
    lies as well on the course of the arm's line ending in the next column, numbered one
    less (``meet_tolerance``); in 65930, on the back proper, a cloth line starts with the
    skin's peak at 0.29 of the height of the line's next two peaks (``end_jump``). Each
    option refuses its peak, and the back keeps its coverage to a thousandth. (Tried as
    version 26, the options caught nothing on fresh held-out frames and stay off.)"""
    bench = _real_bodies()
    for seed, step, objects in (
        (66703, "meet_tolerance", ["left-arm"]),
        (65930, "end_jump", ["trunk"]),
    ):
        frame = _scene(bench, seed, None, stored=True)
        bench._init(None, _on_peaks_5({"numbers": V25}))
        before = bench.score_frame(frame)
        bench._init(None, _on_peaks_5({"numbers": {**V25, step: V26_ENDS[step]}}))
        after = bench.score_frame(frame)
        assert before["wrong_peaks"] == 1 and before["wrong_objects"] == objects
        assert after["wrong_peaks"] == 0
        assert after["back_covered"] >= before["back_covered"] - 0.001 * before["back_crossings"]
        bench._init(None, _on_peaks_5({"numbers": {**V25, **V26_ENDS}}))
        assert bench.score_frame(frame)["wrong_peaks"] == 0


@pytest.mark.slow
def test_a_line_end_turned_onto_its_refused_peaks_course_is_refused_with_the_option() -> None:
    """Clinic scene 67624 (the default code, hands on the hips; frame kept in ``SCENES``,
    rendered on an AMD EPYC): the installed numbering (version 25) on peaks version 5
    numbers the last two peaks of a trunk line wrongly, where the line runs onto the arm:
    they lie on the course of the five refused arm peaks beyond them, off the trunk line's
    own course. With ``course_beyond`` 0.4 both are refused, and the back keeps its
    coverage to a thousandth. (Tried as version 27, the option caught nothing on fresh
    held-out frames and stays off.)"""
    before, after = _kept_scene_scores(
        67624,
        _on_peaks_5({"numbers": V25}),
        _on_peaks_5({"numbers": {**V25, "course_beyond": 0.4}}),
    )
    assert before["wrong_peaks"] == 2 and before["wrong_objects"] == ["right-arm"]
    assert after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] - 0.001 * before["back_crossings"]


#: The block check tried as version 28 (not adopted: BENCHMARKS.md "Real bodies" (41)).
V28_BLOCKS = {"block_gain_share": 0.4, "block_one_shift": True}


@pytest.mark.slow
def test_a_faint_code_s_arm_numbered_a_line_off_is_refused_as_a_block_with_the_options() -> None:
    """Clinic scene 69807 (the faint 45:55 code ``w9-45to55``, arms close, a waistband;
    frame kept in ``SCENES``, rendered on an AMD EPYC): the installed numbering (version 25)
    numbers the whole right arm one line too high (716 peaks, 14 lines), because the block
    check's gain 0.3 per ratio exceeds what this code's reading can gain (log 55/45 =
    0.20). With the gain at 0.4 of the code's contrast, in blocks of one shift, the arm is
    refused, and the back keeps its coverage to two thousandths. (Tried as version 28, the
    options caught nothing on fresh held-out frames nor on a fresh stress set of the faint
    code with the arms close, and stay off.)"""
    before, after = _kept_scene_scores(69807, {"numbers": V25}, {"numbers": {**V25, **V28_BLOCKS}})
    assert before["wrong_peaks"] > 700 and before["wrong_objects"] == ["right-arm"]
    assert after["wrong_peaks"] == 0
    assert after["back_covered"] >= before["back_covered"] - 0.002 * before["back_crossings"]
