"""The compiled best gains of the code bands against the whole-array passes they replaced."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.band_runs import best_gains
from rasterserver_plugins.code_tiles import band_gains

from rasterserver.raster import make_raster

SHIFTS = np.array([0] + [s for s in range(-9, 10) if s != 0])


def _passes(
    c3: np.ndarray, w: np.ndarray, r_off: np.ndarray, diff_at: np.ndarray, shifts: np.ndarray
) -> np.ndarray:
    """``best`` of code_tiles.CodeBands.contradicted: its whole-array passes."""
    return band_gains(c3, w, r_off, diff_at, shifts)[2].max(axis=2)


def _bands(seed: int, n_rows: int = 30, n_lev: int = 40) -> tuple[np.ndarray, ...]:
    """Bands whose differences read the code at their offset, some a block a few levels
    off, under noise; unmeasured levels; offsets near both ends of the code."""
    rng = np.random.default_rng(seed)
    lam, tolerance = float(np.log(1.5)), 0.5
    kinds = make_raster().code.astype(np.int64)
    n_code = kinds.size
    r_off = rng.integers(-5, n_code - n_lev // 2, n_rows)
    place = r_off[:, None] + np.arange(n_lev)[None, :]
    block = rng.random(n_rows) < 0.5
    place[block, n_lev // 2 :] += rng.integers(-3, 4, int(block.sum()))[:, None]
    safe = np.clip(place, 0, n_code - 2)
    d = (kinds[safe] - kinds[safe + 1]) * lam + rng.normal(0, 0.1, place.shape)
    w = rng.uniform(0.0, 1.0, place.shape)
    w[rng.random(place.shape) < 0.15] = 0.0
    expected = np.array([-lam, 0.0, lam])
    u = (d[:, :, None] - expected[None, None, :]) / (tolerance * lam)
    c3 = np.minimum(u * u, 1.0) * w[:, :, None]
    diff_at = np.full(n_code + 1, 3, dtype=np.int64)
    diff_at[: n_code - 1] = kinds[:-1] - kinds[1:] + 1
    return c3, w, r_off.astype(np.int64), diff_at


@pytest.mark.parametrize("seed", range(5))
def test_same_gains_as_the_passes(seed: int) -> None:
    c3, w, r_off, diff_at = _bands(seed)
    want = _passes(c3, w, r_off, diff_at, SHIFTS)
    got = best_gains(c3, w, r_off, diff_at, SHIFTS)
    assert np.any(want >= 2.5) and not np.all(want >= 2.5)  # both decisions occur
    assert got.shape == want.shape and got.tobytes() == want.tobytes()


def test_one_level_one_row_and_a_short_code() -> None:
    c3, w, r_off, diff_at = _bands(7, n_rows=1, n_lev=1)
    for shifts in (SHIFTS, np.array([0, 1])):
        want = _passes(c3, w, r_off, diff_at, shifts)
        assert best_gains(c3, w, r_off, diff_at, shifts).tobytes() == want.tobytes()
    c3, w, r_off, diff_at = _bands(8, n_rows=3, n_lev=12)
    short = diff_at[-6:].copy()  # offsets mostly past the code's end
    want = _passes(c3, w, r_off, short, SHIFTS)
    assert best_gains(c3, w, r_off, short, SHIFTS).tobytes() == want.tobytes()
