"""The compiled scans of the peak detector against the whole-array passes they replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.peak_scan import column_extrema, run_moments


def _extrema_passes(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vectorised extrema of peak_detection before the scan (rasterserver 0.x)."""
    w, h = s.shape
    d = np.empty((w, h), dtype=np.float32)
    np.subtract(s[:, 1:], s[:, :-1], out=d[:, :-1])
    d[:, -1] = 1.0
    flat = d.ravel()
    rising = flat > 0
    nz = np.flatnonzero(rising | (flat < 0))
    up = rising[nz]
    after = nz[1:]
    return after[up[:-1] & ~up[1:]].astype(np.int64), after[~up[:-1] & up[1:]].astype(np.int64)


def _moments_walk(
    tf: np.ndarray, m: np.ndarray, level: np.ndarray, lo: np.ndarray, hi: np.ndarray, half: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The offset-by-offset walk over all maxima at once (rasterserver 0.x)."""
    centre = np.maximum(tf[m] - level, 0.0)
    s0 = centre.astype(np.float64)
    s1 = np.zeros(m.size, dtype=np.float64)
    extent = np.zeros((2, m.size), dtype=np.int16)
    for side, sign in ((0, -1), (1, 1)):
        active = np.flatnonzero(centre > 0)
        bound = lo if sign < 0 else hi
        for j in range(1, half + 1):
            pos = m[active] + sign * j
            v = tf[np.clip(pos, 0, tf.size - 1)] - level[active]
            keep = (v > 0) & (pos * sign <= bound[active] * sign)
            active = active[keep]
            if active.size == 0:
                break
            v = v[keep]
            s0[active] += v
            s1[active] += (sign * j) * v
            extent[side, active] = j
    return s0, s1, extent


def _columns(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    w, h = 40, 120
    rows = np.arange(h, dtype=np.float32)
    s = np.zeros((w, h), dtype=np.float32)
    for c in range(w):
        for centre in rng.uniform(-3, h + 3, 12):
            sigma = rng.uniform(0.6, 3)
            s[c] += rng.uniform(5, 200) * np.exp(-0.5 * ((rows - centre) / sigma) ** 2)
    s += rng.normal(0, 2, s.shape).astype(np.float32)
    s = np.round(np.clip(s, 0, 255))  # 8-bit: plateaus and flat runs
    s[3, 50:60] = 255.0  # a clipped top
    s[5] = 7.0  # a flat column
    s[7, -5:] = [10, 20, 30, 40, 50]  # a peak cut by the frame's edge
    return np.ascontiguousarray(s, dtype=np.float32)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_extrema_as_the_passes(seed: int) -> None:
    s = _columns(seed)
    got, want = column_extrema(s), _extrema_passes(s)
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])
    assert got[0].dtype == np.int64 and got[1].dtype == np.int64


def test_extrema_of_degenerate_frames() -> None:
    for s in (np.zeros((3, 5), np.float32), np.zeros((1, 1), np.float32)):
        maxima, minima = column_extrema(s)
        np.testing.assert_array_equal(maxima, _extrema_passes(s)[0])
        np.testing.assert_array_equal(minima, _extrema_passes(s)[1])
    one = np.array([[0, 1, 5, 1, 0]], np.float32)
    assert column_extrema(one)[0].tolist() == [2]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_moments_as_the_walk(seed: int) -> None:
    s = _columns(seed)
    h = s.shape[1]
    tf = s.ravel()
    maxima, minima = _extrema_passes(s)
    maxima = maxima[(maxima % h > 0) & (maxima % h < h - 1)]
    col_start = (maxima // h) * h
    i = np.searchsorted(minima, maxima)
    lo = np.where(i > 0, np.maximum(minima[np.maximum(i - 1, 0)], col_start), col_start)
    hi = np.minimum(minima[np.minimum(i, minima.size - 1)], col_start + h - 1)
    half = 12
    lo, hi = np.maximum(lo, maxima - half), np.minimum(hi, maxima + half)
    base = np.maximum(tf[lo], tf[hi])
    peak = np.maximum(np.maximum(tf[maxima - 1], tf[maxima]), tf[maxima + 1])
    level = base + np.float32(0.1) * (peak - base)
    # a peak whose window runs to the frame's last pixel: the scan must not read past it
    m = np.append(maxima, tf.size - 2)
    lo, hi = np.append(lo, tf.size - 6), np.append(hi, tf.size - 1)
    level = np.append(level, np.float32(0.0)).astype(np.float32)
    got = run_moments(tf, m, level, lo, hi, half)
    want = _moments_walk(tf, m, level, lo, hi, half)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    assert got[0].dtype == np.float64 and got[2].dtype == np.int16


def test_moments_of_no_peaks() -> None:
    e = np.zeros(0, np.int64)
    s0, _, extent = run_moments(np.zeros(10, np.float32), e, np.zeros(0, np.float32), e, e, 5)
    assert s0.shape == (0,) and extent.shape == (2, 0)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("min_height", [5.0, 5.3, 0.0])
def test_bounded_maxima_as_the_passes(seed: int, min_height: float) -> None:
    from rasterserver_plugins.peak_scan import bounded_maxima

    s = _columns(seed)
    h = s.shape[1]
    sf = s.ravel()
    maxima, minima = _extrema_passes(s)
    col_start = (maxima // h) * h
    i = np.searchsorted(minima, maxima)
    lo = np.where(i > 0, np.maximum(minima[np.maximum(i - 1, 0)], col_start), col_start)
    hi = np.minimum(minima[np.minimum(i, minima.size - 1)], col_start + (h - 1))
    hi = np.where(i < minima.size, hi, col_start + (h - 1))
    top = sf[maxima]
    ok = (top - sf[lo] >= min_height) & (top - sf[hi] >= min_height)  # in float32
    got = bounded_maxima(sf, maxima, minima, h, np.float32(min_height))
    for g, w in zip(got, (maxima[ok], lo[ok], hi[ok]), strict=True):
        np.testing.assert_array_equal(g, w)
    assert 0 < got[0].size < maxima.size or min_height == 0.0
