"""The code read in tiles of a numbered component (blocks of lines placed a level off)."""

from __future__ import annotations

import numpy as np
from image_truth import rendering_raster
from rasterserver_plugins.code_tiles import contradicted_lines

LAM = float(np.log(1.5))


def _component(
    levels: int, width: int, block: tuple[int, int, int] | None = None, seed: int = 0
) -> tuple[np.ndarray, ...]:
    """Peaks (sorted by column, then row) of one component: ``levels`` lines over ``width``
    columns, each line's area the code's width at its true number (offset 10), 3 % noise.
    ``block`` = (first column, first level, shift): in the columns from ``first column``,
    the lines from ``first level`` on are separate lines ordered ``shift`` levels too high
    and the ``shift`` lines above them are hidden (a cloth block below a depth step)."""
    code = rendering_raster().code
    rng = np.random.default_rng(seed)
    cols, areas, lids = [], [], []
    n_lines = levels
    line_order = list(range(levels))
    for c in range(width):
        for k in range(levels):
            true = 10 + k
            lid = k
            if block is not None and c >= block[0]:
                if block[1] - block[2] <= k < block[1]:
                    continue  # hidden by the step
                if k >= block[1]:
                    lid = levels + k - block[1]
            cols.append(c)
            areas.append((1.5 if code[true] else 1.0) * (1.0 + 0.03 * rng.standard_normal()))
            lids.append(lid)
    if block is not None:
        line_order += [k - block[2] for k in range(block[1], levels)]
        n_lines = len(line_order)
    return (
        np.asarray(cols, np.int32),
        np.asarray(areas, np.float32),
        np.asarray(lids, np.int32),
        np.asarray(line_order, np.int32),
        np.zeros(n_lines, np.int32),
    )


def _refused(args: tuple[np.ndarray, ...], offset: int = 10) -> np.ndarray:
    raster = rendering_raster()
    return contradicted_lines(
        *args,
        {0: offset},
        raster.code,
        lam=LAM,
        tolerance=0.5,
        max_cost_rate=0.25,
        min_columns=5,
        correlation=4.0,
    )


def test_a_clean_component_is_not_contradicted() -> None:
    assert not np.any(_refused(_component(40, 200)))


def test_a_block_ordered_a_level_off_is_refused_and_the_rest_kept() -> None:
    # columns 120-199, levels 20-39: separate lines ordered one level too high (line 19
    # hidden there)
    args = _component(40, 200, block=(120, 20, 1))
    refused = _refused(args)
    assert np.all(refused[40:])  # the block's lines
    # the whole lines (their columns 0-119 are right) are kept, except the one just above
    # the step: the tiles over the step see it beside the block
    assert np.flatnonzero(refused[:40]).tolist() in ([], [18])


def test_a_component_placed_wrongly_as_a_whole_is_refused_everywhere() -> None:
    assert np.all(_refused(_component(40, 200), offset=11))


def test_degenerate_inputs() -> None:
    raster = rendering_raster()
    empty = np.zeros(0, np.int32)
    kw = dict(lam=LAM, tolerance=0.5, max_cost_rate=0.25)
    kw2 = dict(min_columns=5, correlation=4.0)
    none = contradicted_lines(
        empty, empty.astype(np.float32), empty, empty, empty, {}, raster.code, **kw, **kw2
    )
    assert none.shape == (0,)
    # numbered nothing: nothing refused
    args = _component(10, 30)
    assert not np.any(_refused(args, offset=-1))
    # one line only: no level differences, nothing to contradict
    args = _component(1, 30)
    assert not np.any(_refused(args))
