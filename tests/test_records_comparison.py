"""The comparison record: the displaced vertices (version 2) are optional, so that version 1
records still load, and checked against the trunk when present."""

from __future__ import annotations

import numpy as np
import pytest

from rasterserver.errors import InputError
from rasterserver.records_comparison import ComparisonRecord


def record(**extra: object) -> ComparisonRecord:
    return ComparisonRecord(
        reason="",
        transform=np.eye(4),
        start=np.eye(4),
        fitness=0.99,
        rmse=0.5,
        points=1000,
        trunk=np.arange(5, dtype=np.int64),
        distance=np.array([0.1, 0.2, np.nan, np.nan, 0.0]),
        **extra,  # type: ignore[arg-type]
    )


def test_a_version_1_record_loads_without_displaced_vertices() -> None:
    old = record()
    arrays = old.to_arrays()
    assert "displaced" not in arrays
    back = ComparisonRecord.from_arrays(arrays)
    assert back.displaced is None and back.content_hash() == old.content_hash()


def test_displaced_vertices_round_trip_and_are_checked() -> None:
    new = record(displaced=np.array([False, False, True, True, False]))
    back = ComparisonRecord.from_arrays(new.to_arrays())
    assert back.displaced is not None and back.displaced.tolist() == [0, 0, 1, 1, 0]
    assert back.content_hash() == new.content_hash() != record().content_hash()
    with pytest.raises(InputError, match="one bool per trunk vertex"):
        record(displaced=np.array([False, True]))
    with pytest.raises(InputError, match="one bool per trunk vertex"):
        record(displaced=np.zeros(5))
