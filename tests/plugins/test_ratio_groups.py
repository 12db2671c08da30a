"""The compiled robust centres against the bincount passes they replaced: the same bits."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.ratio_groups import grouped_centres


def _bincount_passes(
    key: np.ndarray, lr: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """code_evidence.robust_centres of rasterserver 0.x."""
    n_keys = int(key.max()) + 1
    counts = np.bincount(key, minlength=n_keys)
    lr = np.clip(lr, -1.0, 1.0)
    centre = np.bincount(key, weights=lr, minlength=n_keys) / np.maximum(counts, 1)
    for window in (0.3, 0.15):
        near = np.abs(lr - centre[key]) <= window
        total = np.bincount(key[near], weights=lr[near], minlength=n_keys)
        n_near = np.bincount(key[near], minlength=n_keys)
        centre = np.where(n_near > 0, total / np.maximum(n_near, 1), centre)
    spread = np.bincount(key, weights=np.abs(lr - centre[key]), minlength=n_keys) / np.maximum(
        counts, 1
    )
    groups = np.flatnonzero(counts)
    return groups, centre[groups], counts[groups], spread[groups]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_same_bits_as_the_bincount_passes(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = 20000
    key = rng.integers(0, 3000, n) * 3  # gaps: keys not present
    lr = np.where(rng.random(n) < 0.8, rng.normal(0.4, 0.1, n), rng.normal(0, 1.5, n))
    got = grouped_centres(key, lr, np.array([0.3, 0.15]))
    want = _bincount_passes(key, lr)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
        assert g.dtype == w.dtype


def test_one_group_and_none() -> None:
    groups, centre, count, spread = grouped_centres(
        np.array([4, 4, 4]), np.array([0.5, 0.5, 2.0]), np.array([0.3, 0.15])
    )
    assert groups.tolist() == [4] and count.tolist() == [3]
    assert centre.tolist() == [0.5] and spread[0] == pytest.approx(0.5 / 3)
    empty = grouped_centres(np.zeros(0, np.int64), np.zeros(0), np.array([0.3]))
    assert all(a.size == 0 for a in empty)
