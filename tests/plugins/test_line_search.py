"""Line search against the simulator's ground truth and on constructed peak patterns."""

from __future__ import annotations

import numpy as np
import pytest
from image_truth import back, truth_of_peaks, wall
from rasterserver_plugins.line_search import HierarchicalLineSearch, link_peaks, search_lines
from rasterserver_plugins.peak_detection import FirstMomentPeaks

from rasterserver.records import Image
from rasterserver.records_lines import Lines, Peaks
from rasterserver.stage import run_stage


def _peaks(col: np.ndarray, row: np.ndarray, area: np.ndarray | None = None) -> Peaks:
    order = np.lexsort((row, col))
    col, row = np.asarray(col)[order], np.asarray(row, dtype=np.float64)[order]
    area = np.full(col.size, 100.0) if area is None else np.asarray(area)[order]
    n = col.size
    return Peaks(
        col=col.astype(np.int32),
        row=row,
        area=area.astype(np.float32),
        height=np.full(n, 40.0, np.float32),
        width=np.full(n, 7, np.int16),
        image_shape=np.array([600, 600]),
    )


def _lines(peaks: Peaks, **params: object) -> Lines:
    return run_stage(HierarchicalLineSearch, peaks, params)


def _impurity(line_id: np.ndarray, number: np.ndarray) -> tuple[int, int]:
    """Lines holding peaks of more than one true line; peaks not of their line's majority."""
    impure = wrong = 0
    for line in np.unique(line_id[line_id >= 0]):
        truth = number[(line_id == line) & (number >= 0)]
        if truth.size == 0:
            continue
        _, counts = np.unique(truth, return_counts=True)
        if counts.size > 1:
            impure += 1
            wrong += int(truth.size - counts.max())
    return impure, wrong


@pytest.mark.parametrize("name", ["normal", "severe"])
def test_simulated_back_lines_are_pure(name: str) -> None:
    r = back(name)
    peaks = run_stage(FirstMomentPeaks, Image(r.image))
    lines = _lines(peaks)
    number, _ = truth_of_peaks(lines.col, lines.row, r.line_rows)
    assert _impurity(lines.line_id, number) == (0, 0)
    in_line = lines.line_id >= 0
    assert in_line[number >= 0].mean() > 0.99
    # lines are long: most peaks are in lines of 40 columns or more
    sizes = np.bincount(lines.line_id[in_line])
    assert np.mean(sizes[lines.line_id[in_line]] >= 40) > 0.9


def test_flat_wall_gives_one_line_per_raster_line() -> None:
    r = wall()
    peaks = run_stage(FirstMomentPeaks, Image(r.image))
    lines = _lines(peaks)
    number, _ = truth_of_peaks(lines.col, lines.row, r.line_rows)
    assert _impurity(lines.line_id, number) == (0, 0)
    width = int(peaks.image_shape[1])
    sizes = np.bincount(lines.line_id[lines.line_id >= 0])
    full = sizes >= 0.95 * width
    assert full.sum() >= np.unique(r.line_rows.number).size - 2


def test_sharp_corner_cuts_a_line() -> None:
    col = np.arange(100)
    # a smooth line whose right half is displaced by 3 px: a false interconnection
    row = 100.0 + 0.1 * col + np.where(col >= 50, 3.0, 0.0)
    lines = _lines(_peaks(col, row))
    ids = lines.line_id[np.argsort(lines.col)]
    assert ids[0] != ids[-1]
    assert np.all(ids[:49] == ids[0]) and np.all(ids[51:] == ids[-1])


def test_intensity_minimum_cuts_a_smooth_line() -> None:
    # Smooth and continuous, but the intensity falls to a pronounced minimum at column 60:
    # the shoulder-blade case.
    col = np.arange(120)
    row = 200.0 + 5.0 * np.sin(col / 40.0)
    area = 200.0 * (1.0 - 0.8 * np.exp(-0.5 * ((col - 60) / 4.0) ** 2))
    lines = _lines(_peaks(col, row, area))
    ids = lines.line_id[np.argsort(lines.col)]
    assert ids[0] >= 0 and ids[-1] >= 0 and ids[0] != ids[-1]
    assert np.all(ids[:50] == ids[0]) and np.all(ids[70:] == ids[-1])


def test_area_step_cuts_a_smooth_line() -> None:
    # Smooth and continuous, but the area doubles at column 60 and stays there: a change of
    # surface (skin to clothing), where the depth may step by a whole line spacing.
    col = np.arange(120)
    row = 200.0 + 0.3 * col
    area = np.where(col < 60, 100.0, 230.0)
    lines = _lines(_peaks(col, row, area))
    ids = lines.line_id[np.argsort(lines.col)]
    assert ids[0] >= 0 and ids[-1] >= 0 and ids[0] != ids[-1]
    assert np.all(ids[:58] == ids[0]) and np.all(ids[62:] == ids[-1])
    # the step cut can be switched off
    off = run_stage(HierarchicalLineSearch, _peaks(col, row, area), params={"step_ratio": None})
    assert np.unique(off.line_id).tolist() == [0]


def test_moderate_area_change_keeps_one_line() -> None:
    # shading and light/heavy-like changes below the step ratio do not cut
    col = np.arange(120)
    row = 200.0 + 0.3 * col
    area = np.where(col < 60, 100.0, 170.0)
    lines = _lines(_peaks(col, row, area))
    assert np.unique(lines.line_id).tolist() == [0]


def test_gradual_shading_keeps_one_line() -> None:
    col = np.arange(300)
    row = 150.0 + 0.02 * (col - 150.0) ** 2 / 10.0
    area = np.linspace(400.0, 40.0, col.size)
    lines = _lines(_peaks(col, row, area))
    assert np.unique(lines.line_id).tolist() == [0]


def test_parallel_lines_stay_apart() -> None:
    col = np.tile(np.arange(80), 5)
    row = np.repeat(np.arange(5) * 9.0 + 50.0, 80) + 0.4 * np.sin(col / 9.0)
    lines = _lines(_peaks(col, row))
    assert lines.n_lines == 5
    for k in range(5):
        sel = np.abs(lines.row - (50.0 + 9.0 * k)) < 2
        assert np.unique(lines.line_id[sel]).size == 1


def test_links_are_mutual() -> None:
    col = np.array([0, 1, 1])
    row = np.array([10.0, 9.0, 10.5])
    right, left = link_peaks(col, row)
    assert right.tolist() == [2, -1, -1]
    assert left.tolist() == [-1, -1, 0]


def test_empty_and_tiny_inputs() -> None:
    assert _lines(_peaks(np.zeros(0, int), np.zeros(0))).n_lines == 0
    assert _lines(_peaks(np.array([3]), np.array([5.0]))).line_id.tolist() == [-1]
    # one column: no links, no lines
    one = _lines(_peaks(np.zeros(4, int), np.arange(4) * 10.0))
    assert np.all(one.line_id == -1)
    # one row of columns carrying a single line
    row_line = search_lines(np.arange(6), np.full(6, 0.2), np.ones(6))
    assert row_line.tolist() == [0] * 6


def test_version_is_bumped() -> None:
    # 3: turn cuts and vertex cuts by default
    assert HierarchicalLineSearch.version == "3"
    defaults = HierarchicalLineSearch.Params()
    assert defaults.turn == 1.3 and defaults.turn_half == 3 and defaults.vertex


def test_output_keeps_the_peaks() -> None:
    peaks = _peaks(np.arange(20), np.full(20, 30.0))
    lines = _lines(peaks)
    for name in ("col", "row", "area", "height", "width", "image_shape"):
        assert np.array_equal(getattr(lines, name), getattr(peaks, name))
    assert lines.line_id.dtype == np.int32


def _rounded_v(col: np.ndarray) -> np.ndarray:
    """A line running down at 0.6 px per column onto another surface's line running up at
    1.2 px per column, the vertex rounded over two links (as 62875's junction: steps 0.75,
    -1.61, -1.09): no link departs by 1.5 px from the steps beside it."""
    step = np.where(col < 60, 0.6, -1.2)
    step[col == 60] = -0.3  # the peak at the contour lies between both courses
    return 300.0 + np.cumsum(step)


def test_turn_cuts_a_line_running_onto_another_surface() -> None:
    col = np.arange(100)
    row = _rounded_v(col)
    # the corner alone keeps the chain: the vertex is rounded (version 2)
    kept = _lines(_peaks(col, row), turn=None)
    assert np.unique(kept.line_id).tolist() == [0]
    for cut in (_lines(_peaks(col, row), turn=1.0), _lines(_peaks(col, row))):
        ids = cut.line_id[np.argsort(cut.col)]
        assert ids[0] >= 0 and ids[-1] >= 0 and ids[0] != ids[-1]
        assert np.all(ids[:58] == ids[0]) and np.all(ids[62:] == ids[-1])


def test_turn_keeps_smooth_curved_lines() -> None:
    # a line bending towards a silhouette: its step grows from 0 to 2.5 px per column over
    # 100 columns, and a gentle spinal furrow's V of 0.3 px per column either side
    col = np.arange(100)
    bend = 200.0 + 0.0125 * col**2
    furrow = 400.0 + 0.3 * np.abs(col - 50.0)
    for row in (bend, furrow):
        for turn in (1.0, 1.3):
            lines = _lines(_peaks(col, row), turn=turn)
            assert np.unique(lines.line_id).tolist() == [0]


def test_turn_on_short_and_degenerate_chains() -> None:
    # chains shorter than the two sides' links are never judged; no peaks give no lines
    col = np.arange(6)
    row = np.array([10.0, 11.0, 12.0, 11.0, 10.0, 9.0])
    assert np.unique(_lines(_peaks(col, row), turn=0.5).line_id).tolist() == [0]
    empty = _lines(_peaks(np.zeros(0, np.int32), np.zeros(0)), turn=1.0)
    assert empty.line_id.size == 0


def test_vertex_peak_joins_neither_line() -> None:
    # two surfaces' lines meeting in a V at column 50, the vertex peak between both
    # courses: the corner cut leaves it to one of them; with ``vertex`` it is in neither
    col = np.arange(100)
    step = np.where(col < 50, 1.2, -3.0)
    step[50] = 0.6
    row = 300.0 + np.cumsum(step)
    plain = _lines(_peaks(col, row), vertex=False, turn=None)
    ids = plain.line_id[np.argsort(plain.col)]
    assert ids[0] != ids[-1] and ids[50] in (ids[0], ids[-1])
    for cut in (_lines(_peaks(col, row), vertex=True, turn=None), _lines(_peaks(col, row))):
        ids = cut.line_id[np.argsort(cut.col)]
        assert ids[50] == -1
        assert np.all(ids[:50] == ids[0]) and np.all(ids[51:] == ids[-1]) and ids[0] != ids[-1]
