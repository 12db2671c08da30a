"""The compiled line lookup of the points stage against the passes it replaced: same bits."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from image_truth import station
from rasterserver_plugins.line_planes import gathered_planes
from rasterserver_plugins.reconstruction import _line_index, _line_planes

from rasterserver.raster import make_raster


def _passes(projector, raster, number: np.ndarray) -> tuple:  # type: ignore[no-untyped-def]
    """reconstruction._line_planes of rasterserver 0.x."""
    positions, k, known = _line_index(raster, number)
    if positions.size == 0:
        nan = np.full(k.shape, np.nan)
        return nan, projector.light_plane(nan)
    positions = np.asarray(positions, dtype=np.float64)
    v = np.where(known, positions[k], np.nan)
    normals, offsets = projector.light_plane(positions)
    n_w, off = normals[k], offsets[k]
    n_w[~known] = np.nan
    off[~known] = np.nan
    return v, (n_w, off)


def _same(got: tuple, want: tuple) -> None:
    (gv, (gn, go)), (wv, (wn, wo)) = got, want
    for g, w in ((gv, wv), (gn, wn), (go, wo)):
        assert g.dtype == w.dtype and g.shape == w.shape and g.tobytes() == w.tobytes()


@pytest.mark.parametrize("seed", range(3))
def test_same_planes(seed: int) -> None:
    projector = station().projector
    rng = np.random.default_rng(seed)
    for raster in (station().raster_definition, make_raster(40, first_number=7)):
        number = rng.integers(-3, raster.numbers.max() + 4, 5000)
        _same(_line_planes(projector, raster, number), _passes(projector, raster, number))


def test_unsorted_and_repeated_numbers() -> None:
    projector = station().projector
    raster = make_raster(30)
    numbers = raster.numbers.copy()
    numbers[5:10] = numbers[5:10][::-1]  # not in order
    numbers[20] = numbers[21]  # a number twice: the first in order is taken
    shuffled = dataclasses.replace(raster, numbers=numbers)
    number = np.arange(-2, 40)
    _same(_line_planes(projector, shuffled, number), _passes(projector, shuffled, number))
    _same(_line_planes(projector, raster, number[:0]), _passes(projector, raster, number[:0]))


def test_kernel_on_one_line() -> None:
    v, n_w, off = gathered_planes(
        np.array([4]), np.array([2.5]), np.ones((1, 3)), np.array([7.0]), np.array([3, 4, 5])
    )
    assert np.isnan(v[[0, 2]]).all() and v[1] == 2.5 and off[1] == 7.0
    assert np.isnan(n_w[[0, 2]]).all() and n_w[1].tolist() == [1.0, 1.0, 1.0]
