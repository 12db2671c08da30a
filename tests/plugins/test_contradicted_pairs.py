"""The pair check's entry in the numbering's reasons (the pair tests themselves, on stacks
of synthetic lines, are in ``test_numbering_refusals.py`` beside the other refusals)."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.contradicted_pairs import PairRule, pair_refusal
from test_numbering_refusals import LAM, _stack

from rasterserver.raster import get_raster


def test_the_refused_lines_are_counted_with_their_reason() -> None:
    """A cloth block numbered a line low (scene 7728's case): version 21's rule spares it
    and gives no entry; version 22's refuses its three lines (blocks of up to 40 peaks
    here, the synthetic lines being long) and says why."""
    raster = get_raster("w8-1to2")
    extents = [(0, 40), (0, 28), (18, 40), (10, 40), (0, 40)]
    data, numbers = _stack(
        extents, [1.0, 2.0, 2.0, 2.0, 2.0], raster, first=18, shown=[18, 20, 21, 22, 23]
    )
    per_line = np.bincount(data.line_id, minlength=numbers.size)
    kept = numbers.copy()
    assert pair_refusal(data, raster, LAM, kept, per_line, PairRule()) is None
    assert np.array_equal(kept, numbers)
    line_number = numbers.copy()
    entry = pair_refusal(data, raster, LAM, line_number, per_line, PairRule(shift=True, block=40))
    assert entry is not None and entry.component == -1 and entry.n_levels == 3
    assert "contradicts the code at their numbers" in entry.reason
    assert np.flatnonzero(line_number < 0).tolist() == [2, 3, 4]
