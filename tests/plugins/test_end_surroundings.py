"""A long line's end among unnumbered peaks: refused where the line runs onto a refused surface."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.end_surroundings import ends_among_unnumbered

SPACING = 8.0


def _peaks(
    lines: list[tuple[int, int, int, float, bool]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Peaks of horizontal lines ``(line_id, first_col, last_col, row, numbered)``, numbered
    by their id when ``numbered``, sorted by ``(col, row)``."""
    col, row, lid, num = [], [], [], []
    for line, c0, c1, r, numbered in lines:
        cols = np.arange(c0, c1 + 1)
        col.append(cols)
        row.append(np.full(cols.size, r))
        lid.append(np.full(cols.size, line))
        num.append(np.full(cols.size, line if numbered else -1))
    c, r, l_, n = (np.concatenate(a) for a in (col, row, lid, num))
    order = np.lexsort((r, c))
    return c[order], r[order], l_[order].astype(np.int32), n[order].astype(np.int32)


def _refused(col, row, lid, number, **kw) -> np.ndarray:
    return ends_among_unnumbered(col, row, lid, number, np.full(col.size, SPACING), **kw)


def _back_and_cloth() -> tuple[np.ndarray, ...]:
    """Five numbered back lines ending at column 199, at a cloth's side edge; the cloth's
    unnumbered lines start at column 216, but the middle line runs on without a gap
    across the edge to meet them (the cloth showing the next raster line at its row)."""
    back = [(k, 0, 215 if k == 12 else 199, 8.0 * k, True) for k in range(10, 15)]
    cloth = [(100 + k, 216, 280, 8.0 * k, False) for k in range(10, 15)]
    return _peaks(back + cloth)


def test_a_long_lines_end_among_a_refused_surface_is_refused() -> None:
    col, row, lid, number = _back_and_cloth()
    refused = _refused(col, row, lid, number, reach=12, share=0.4, min_length=80, passes=1)
    # the piece the middle line carries across the edge goes where the cloth outnumbers
    # the back around it; the back and the other lines' ends at the edge stay
    assert np.all(lid[refused] == 12)
    assert set(col[refused].tolist()) == set(range(208, 216))


def test_one_pass_judges_only_the_ends_and_passes_erode_a_longer_piece() -> None:
    col, row, lid, number = _back_and_cloth()
    one = _refused(col, row, lid, number, reach=4, share=0.4, min_length=80, passes=1)
    three = _refused(col, row, lid, number, reach=4, share=0.4, min_length=80, passes=3)
    assert one.sum() == 4 and set(col[one].tolist()) == {212, 213, 214, 215}
    assert three.sum() == 10 and set(col[three].tolist()) == set(range(206, 216))
    # eroded until the back's numbered lines outnumber the cloth around the new end
    more = _refused(col, row, lid, number, reach=4, share=0.4, min_length=80, passes=9)
    assert np.array_equal(more, three)


def test_ends_at_a_silhouette_are_kept() -> None:
    # every line ends at column 199 with nothing beyond (the background has no peaks)
    col, row, lid, number = _peaks([(k, 0, 199, 8.0 * k, True) for k in range(10, 15)])
    assert not np.any(_refused(col, row, lid, number, reach=12, share=0.4, min_length=80))


def test_short_lines_are_not_judged() -> None:
    """Dashes in hair end among the unnumbered fragments beside them: a strand, not an edge."""
    col, row, lid, number = _back_and_cloth()
    assert not np.any(_refused(col, row, lid, number, reach=12, share=0.4, min_length=300))


def test_the_share_decides() -> None:
    col, row, lid, number = _back_and_cloth()
    assert not np.any(_refused(col, row, lid, number, reach=12, share=0.99, min_length=80))


def test_degenerate_inputs_refuse_nothing() -> None:
    col, row, lid, number = _back_and_cloth()
    assert not np.any(ends_among_unnumbered(col, row, lid, number, None))
    assert not np.any(_refused(col, row, lid, number, reach=0))
    empty = np.zeros(0)
    none = ends_among_unnumbered(
        empty.astype(np.int32), empty, empty.astype(np.int32), empty.astype(np.int32), empty
    )
    assert none.shape == (0,)
    unnumbered = np.full(col.size, -1, np.int32)
    assert not np.any(_refused(col, row, lid, unnumbered))


def test_later_passes_judging_only_what_changed_refuse_what_full_passes_refuse() -> None:
    """Passes two and three judge again only the end peaks whose line lost peaks or whose
    square holds a peak refused since: the same refusals as judging every end each time."""
    from rasterserver_plugins.end_surroundings import _one_pass

    rng = np.random.default_rng(13)
    for trial in range(20):
        lines = []
        for k in range(12):
            c0 = int(rng.integers(0, 60))
            c1 = c0 + int(rng.integers(20, 260))
            lines.append((k, c0, c1, SPACING * k + rng.normal(0, 0.5), bool(rng.random() < 0.7)))
        col, row, lid, number = _peaks(lines)
        spacing = np.full(col.size, SPACING)
        kw = dict(reach=6, share=0.3, window=2.0, min_length=40)
        full = np.zeros(col.size, dtype=bool)
        for _ in range(4):
            more = _one_pass(col, row, lid, np.where(full, -1, number), spacing, **kw)
            if not np.any(more):
                break
            full |= more
        fast = ends_among_unnumbered(col, row, lid, number, spacing, passes=4, **kw)
        assert np.array_equal(fast, full), trial
