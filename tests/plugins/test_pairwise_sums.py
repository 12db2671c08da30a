"""The compiled pairwise sum against numpy's sum along a contiguous axis: the same bits."""

from __future__ import annotations

import numpy as np
import pytest
from rasterserver_plugins.pairwise_sums import pairwise_sum


@pytest.mark.parametrize("n", [0, 1, 3, 7, 8, 9, 15, 16, 17, 127, 128, 129, 300, 1025, 40001])
def test_same_bits_as_numpy(n: int) -> None:
    rng = np.random.default_rng(n)
    # magnitudes over 16 decades: any other order of the additions rounds differently
    x = rng.normal(size=(4, n)) * 10.0 ** rng.integers(-8, 8, size=(4, n))
    want = x.sum(axis=1)
    for i in range(4):
        assert np.float64(pairwise_sum(x[i], 0, n)).tobytes() == want[i].tobytes()


def test_a_slice_and_signed_zeros() -> None:
    x = np.random.default_rng(0).normal(size=500) * 1e6
    assert pairwise_sum(x, 17, 300) == x[17:317].sum()
    for n in (3, 9):
        zeros = np.full(n, -0.0)
        assert np.float64(pairwise_sum(zeros, 0, n)).tobytes() == zeros.sum().tobytes()
