"""The ground-floor hashing module: digests pinned, so stored provenance keeps its meaning."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest

from rasterserver.hashing import (
    canonical_array,
    canonical_json,
    canonical_json_sha256,
    frame_sha256,
)


def test_canonical_json_sorts_keys_and_drops_whitespace() -> None:
    assert canonical_json({"b": [1, 2.5], "a": "é"}) == '{"a":"\\u00e9","b":[1,2.5]}'
    assert canonical_json({"a": "é"}, ensure_ascii=False) == '{"a":"é"}'
    with pytest.raises(ValueError):
        canonical_json({"x": float("nan")})
    assert canonical_json({"x": float("nan")}, allow_nan=True) == '{"x":NaN}'


def test_pinned_digests() -> None:
    # the digests stored in catalogues made before the move: they must never change
    assert canonical_json_sha256({"b": 1, "a": [1, 2]}) == hashlib.sha256(
        b'{"a":[1,2],"b":1}').hexdigest()
    frame = np.arange(12, dtype=">u2").reshape(3, 4)
    assert frame_sha256(frame) == hashlib.sha256(
        np.arange(12, dtype="<u2").tobytes()).hexdigest()
    assert frame_sha256(frame.T) == frame_sha256(np.ascontiguousarray(frame.T))


@pytest.mark.parametrize("array", [
    np.arange(6, dtype=">f8").reshape(2, 3)[:, ::2],
    np.float64(2.5),
    np.array(3, dtype=">i4"),
    np.array(["ab", "c"]),
    np.array([True, False]),
])
def test_canonical_array_is_the_records_layout(array: np.ndarray) -> None:
    """What Record.content_hash hashed before the move (records._canonical)."""
    before = np.ascontiguousarray(array)
    if before.dtype.str.startswith(">"):
        before = before.astype(before.dtype.newbyteorder("<"))
    after = canonical_array(array)
    assert (after.dtype.str, after.shape, after.tobytes()) == (
        before.dtype.str, before.shape, before.tobytes())


def test_the_ground_floor_imports_nothing_heavy() -> None:
    code = ("import sys, rasterserver.hashing; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('numpy', 'sqlalchemy') or m.startswith('rasterserver.') "
            "and m != 'rasterserver.hashing'))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          check=True)
    assert json.loads(done.stdout.replace("'", '"')) == []
