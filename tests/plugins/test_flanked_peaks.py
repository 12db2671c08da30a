"""Flanked peaks: a line's peak a neighbouring bump made untrustworthy is kept where the
line's trusted peaks flank it; nothing else is (hand-made frames through the detector and
the stage)."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.flanked_peaks import FlankRule, flanked
from rasterserver_plugins.peak_detection import FirstMomentPeaks, PeakArrays, detect_peaks

from rasterserver.records import Image
from rasterserver.stage import run_stage


def _frame(bump_row: float = 34.5, dim_right: bool = False, gaps: bool = False) -> np.ndarray:
    """A line at row 30.3 over 12 columns; in column 5 alone a second line at ``bump_row``
    makes the first one's bounding minima unequal (the detector drops it there)."""
    y = np.arange(64, dtype=float)[:, None]
    img = np.tile(20 + 150 * np.exp(-0.5 * ((y - 30.3) / 1.2) ** 2), (1, 12))
    img[:, 5] += 90 * np.exp(-0.5 * ((y[:, 0] - bump_row) / 1.2) ** 2)
    if dim_right:  # another surface from column 6 on: half the light
        img[:, 6:] = 20 + (img[:, 6:] - 20) * 0.5
    if gaps:  # the line does not run on two columns out
        img[:, [3, 7]] = 20
    return np.clip(img, 0, 255).astype(np.uint8)


def _at(peaks: PeakArrays, col: int) -> list[float]:
    return [round(float(r), 1) for c, r in zip(peaks.col, peaks.row, strict=True) if c == col]


def test_a_dropped_peak_flanked_by_its_line_is_kept() -> None:
    img = _frame()
    without = detect_peaks(img)
    assert _at(without, 5) == [] and without.dropped == 2
    kept = detect_peaks(img, flank_rule=FlankRule())
    assert _at(kept, 5) == [30.3]  # the line's peak; the lone bump stays dropped
    assert kept.dropped == 1
    assert np.all(np.diff(kept.col) >= 0)  # still sorted by column
    before = set(zip(without.col.tolist(), without.row.tolist(), strict=True))
    assert before <= set(zip(kept.col.tolist(), kept.row.tolist(), strict=True))
    # no tolerance: nothing kept
    none = detect_peaks(img, flank_rule=FlankRule(tolerance=0.0))
    assert none.col.tolist() == without.col.tolist() and none.dropped == 2


def test_the_stage_keeps_it_by_default_and_not_with_tolerance_0() -> None:
    img = _frame()
    stage = run_stage(FirstMomentPeaks, Image(img))
    assert [round(float(r), 1) for r in stage.row[stage.col == 5]] == [30.3]
    assert stage.dropped == 1
    off = run_stage(FirstMomentPeaks, Image(img), {"flank_tolerance": 0.0})
    assert off.row[off.col == 5].size == 0 and off.dropped == 2


def test_flanks_of_unequal_area_or_a_line_that_does_not_run_on_keep_nothing() -> None:
    # an arm's edge: the flanks differ by twice in area
    assert _at(detect_peaks(_frame(dim_right=True), flank_rule=FlankRule()), 5) == []
    wide = FlankRule(area_ratio=2.5)
    assert _at(detect_peaks(_frame(dim_right=True), flank_rule=wide), 5) == [30.3]
    # the line ends two columns out: kept only without the run-on test
    assert _at(detect_peaks(_frame(gaps=True), flank_rule=FlankRule()), 5) == []
    loose = FlankRule(run_on=0.0)
    assert _at(detect_peaks(_frame(gaps=True), flank_rule=loose), 5) == [30.3]


def test_dim_or_clipped_peaks_are_never_kept() -> None:
    # the flanked peak's top clipped over two pixels: dropped for that, not for crowding
    img = _frame().astype(np.float32)
    img[29:32, 5] = 255.0
    kept = detect_peaks(img, flank_rule=FlankRule(), clip_level=255.0)
    assert _at(kept, 5) == [] and kept.dropped == 2
    # the same frame from a camera that does not clip there: kept
    assert len(_at(detect_peaks(img, flank_rule=FlankRule()), 5)) == 1
    # a dim line: its peaks are all untrusted, none flanks another
    dim = (20 + (_frame().astype(np.float32) - 20) * 0.015).astype(np.float32)
    assert detect_peaks(dim, flank_rule=FlankRule()).col.size == 0


def test_degenerate_inputs() -> None:
    rule = FlankRule()
    empty = np.zeros(0)
    none = np.zeros(0, dtype=bool)
    assert flanked(empty, empty, empty, none, none, rule, 10).size == 0
    # a candidate with fewer than two trusted peaks, or none to keep: nothing
    one = np.array([True, False])
    cand = np.array([False, True])
    cols, rows, areas = np.array([0.0, 1.0]), np.array([5.0, 5.0]), np.ones(2)
    assert not flanked(cols, rows, areas, one, cand, rule, 10).any()
    # a flat frame and a frame of one column
    assert detect_peaks(np.full((32, 8), 40, np.uint8), flank_rule=rule).col.size == 0
    assert detect_peaks(_frame()[:, 5:6], flank_rule=rule).col.size == 0
