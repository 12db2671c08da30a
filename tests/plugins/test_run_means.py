"""The compiled runs and means of the line smoothing against the passes they replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.smoothing import smooth_along_lines

from rasterserver.records_surface import Points


def _passes(points: Points, window: int = 3, step: int = 3, max_jump: float = 5.0) -> Points:
    """smoothing.smooth_along_lines of rasterserver 0.x (for a run with centres)."""
    n = len(points)
    width = int(points.col.max()) + 2
    key = points.number.astype(np.int64) * width + points.col.astype(np.int64)
    order = np.argsort(key, kind="stable")
    number = points.number[order]
    col = points.col[order].astype(np.int64)
    xyz = np.column_stack([points.x[order], points.y[order], points.z[order]])
    jump = np.einsum("ij,ij->i", np.diff(xyz, axis=0), np.diff(xyz, axis=0)) > max_jump**2
    start = np.ones(n, dtype=bool)
    start[1:] = (np.diff(col) != 1) | (number[1:] != number[:-1]) | jump
    run = np.cumsum(start) - 1
    run_first = np.flatnonzero(start)
    run_len = np.diff(np.append(run_first, n))
    pos = np.arange(n) - run_first[run]
    half = window // 2
    centre = (pos >= half) & ((pos - half) % step == 0) & (pos + half < run_len[run])
    idx = np.flatnonzero(centre)
    members = order[idx[None, :] + np.arange(-half, half + 1)[:, None]]

    def mean(values: np.ndarray) -> np.ndarray:
        return values[members].sum(axis=0, dtype=np.float64) / window

    return Points(
        x=mean(points.x),
        y=mean(points.y),
        z=mean(points.z),
        number=np.ascontiguousarray(number[idx], dtype=np.int32),
        col=col[idx].astype(np.int32),
        row=mean(points.row),
        area=mean(points.area).astype(np.float32),
        image_shape=points.image_shape.copy(),
        reason=points.reason,
    )


def _points(seed: int) -> Points:
    """Lines of peaks over 300 columns with gaps, doubled columns and depth steps, in a
    shuffled order."""
    rng = np.random.default_rng(seed)
    cols, numbers = [], []
    for line in range(30):
        c = np.arange(int(rng.integers(0, 80)), int(rng.integers(150, 300)))
        c = c[rng.random(c.size) < 0.93]
        c = np.concatenate([c, rng.choice(c, 3)])  # a second peak in a few columns
        cols.append(c)
        numbers.append(np.full(c.size, 10 + line))
    col = np.concatenate(cols)
    number = np.concatenate(numbers)
    n = col.size
    z = 50.0 * np.sin(col / 60.0) + np.where(rng.random(n) < 0.01, 30.0, 0.0)
    perm = rng.permutation(n)
    return Points(
        x=(col * 1.7 + rng.normal(0, 0.2, n))[perm],
        y=(number * 10.0 + rng.normal(0, 0.2, n))[perm],
        z=(z + rng.normal(0, 0.3, n))[perm],
        number=number.astype(np.int32)[perm],
        col=col.astype(np.int32)[perm],
        row=(number * 9.0 + rng.normal(0, 0.4, n))[perm],
        area=rng.uniform(50, 500, n).astype(np.float32)[perm],
        image_shape=np.array([400, 320], dtype=np.int64),
        reason="",
    )


def _same(got: Points, want: Points) -> None:
    for name in ("x", "y", "z", "number", "col", "row", "area"):
        g, w = getattr(got, name), getattr(want, name)
        assert g.dtype == w.dtype and g.tobytes() == w.tobytes(), name


@pytest.mark.parametrize("seed", range(3))
def test_same_means(seed: int) -> None:
    points = _points(seed)
    for window, step, max_jump in ((3, 3, 5.0), (5, 2, 5.0), (1, 1, 5.0), (3, 1, 2.0)):
        want = _passes(points, window, step, max_jump)
        assert len(want) > 100
        _same(smooth_along_lines(points, window=window, step=step, max_jump=max_jump), want)


def test_one_point_and_runs_too_short() -> None:
    points = _points(4).take(np.arange(1))
    _same(smooth_along_lines(points, window=1), _passes(points, window=1))
    assert len(smooth_along_lines(points)) == 0
    short = _points(5)
    assert len(smooth_along_lines(short, window=401)) == 0


@pytest.mark.parametrize("seed", range(3))
def test_end_blocks_only_add_points(seed: int) -> None:
    # every point of the steps is kept, bit for bit; the end blocks come on top, one at most
    # per run, each within window // 2 columns of its run's last peak
    points = _points(seed)
    for window, step in ((3, 3), (5, 2), (3, 1)):
        plain = smooth_along_lines(points, window=window, step=step)
        ends = smooth_along_lines(points, window=window, step=step, end_blocks=True)
        key = {(int(n), int(c)) for n, c in zip(plain.number, plain.col, strict=True)}
        extra = [
            i
            for i, (n, c) in enumerate(zip(ends.number, ends.col, strict=True))
            if (int(n), int(c)) not in key
        ]
        kept = np.setdiff1d(np.arange(len(ends)), extra)
        assert np.array_equal(ends.z[kept], plain.z)
        if step == 1:
            assert extra == []  # every peak with neighbours is a centre already
        else:
            assert 0 < len(extra) < len(plain)
