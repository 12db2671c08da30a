"""The records of the image-processing stages: validation, inheritance, round trips."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from rasterserver.errors import InputError
from rasterserver.records import record_type
from rasterserver.records_lines import Lines, NumberedLines, OrderedLines, Peaks


def _peak_fields(n: int = 4) -> dict[str, Any]:
    return {
        "col": np.array([0, 0, 1, 1][:n], dtype=np.int32),
        "row": np.array([3.2, 13.1, 3.4, 13.0][:n]),
        "area": np.full(n, 100.0, np.float32),
        "height": np.full(n, 40.0, np.float32),
        "width": np.full(n, 7, np.int16),
        "image_shape": np.array([20, 2], dtype=np.int64),
    }


def _numbered_fields() -> dict[str, Any]:
    return _peak_fields() | {
        "line_id": np.array([0, 1, 0, 1], np.int32),
        "order": np.array([0, 1, 0, 1], np.int32),
        "line_order": np.array([0, 1], np.int32),
        "line_component": np.array([0, 0], np.int32),
        "number": np.array([40, 41, 40, 41], np.int32),
        "line_number": np.array([40, 41], np.int32),
        "kind_observed": np.array([0, 1], np.int8),
        "confidence": 0.9,
        "reason": "",
    }


def test_kinds_are_registered() -> None:
    assert record_type("peaks") is Peaks
    assert record_type("lines") is Lines
    assert record_type("ordered-lines") is OrderedLines
    assert record_type("numbered-lines") is NumberedLines


def test_each_record_extends_the_previous() -> None:
    rec = NumberedLines(**_numbered_fields())
    assert isinstance(rec, OrderedLines) and isinstance(rec, Lines) and isinstance(rec, Peaks)
    assert rec.n_peaks == 4
    assert rec.n_lines == 2


def test_round_trip_through_arrays() -> None:
    rec = NumberedLines(**_numbered_fields())
    again = NumberedLines.from_arrays(rec.to_arrays())
    assert again == rec
    assert again.content_hash() == rec.content_hash()


def test_empty_records_are_valid() -> None:
    empty = {
        "col": np.zeros(0, np.int32),
        "row": np.zeros(0),
        "area": np.zeros(0, np.float32),
        "height": np.zeros(0, np.float32),
        "width": np.zeros(0, np.int16),
        "image_shape": np.array([5, 5]),
    }
    assert Peaks(**empty).n_peaks == 0
    lines = Lines(**empty, line_id=np.zeros(0, np.int32))
    assert lines.n_lines == 0


def test_unsorted_peaks_are_refused() -> None:
    fields = _peak_fields()
    fields["row"] = np.array([13.1, 3.2, 3.4, 13.0])
    with pytest.raises(InputError, match="sorted"):
        Peaks(**fields)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("row", np.zeros(3)),
        ("col", np.zeros(4, np.float64)),
        ("image_shape", np.array([1, 2, 3])),
    ],
)
def test_bad_peak_arrays_are_refused(field: str, value: np.ndarray) -> None:
    fields = _peak_fields() | {field: value}
    with pytest.raises(InputError):
        Peaks(**fields)


def test_line_tables_must_match() -> None:
    fields = _numbered_fields()
    fields["line_number"] = np.array([40], np.int32)
    with pytest.raises(InputError, match="line_number"):
        NumberedLines(**fields)
    fields = _numbered_fields()
    fields["line_id"] = np.array([0, 1, 0, -2], np.int32)
    with pytest.raises(InputError, match="line_id"):
        NumberedLines(**fields)


def test_confidence_range() -> None:
    with pytest.raises(InputError, match="confidence"):
        NumberedLines(**(_numbered_fields() | {"confidence": 1.5}))


def test_dropped_count_is_optional_and_keeps_old_hashes() -> None:
    plain = Peaks(**_peak_fields())
    assert plain.dropped is None and "dropped" not in plain.to_arrays()
    counted = Peaks(**_peak_fields(), dropped=3)
    assert Peaks.from_arrays(counted.to_arrays()).dropped == 3
    assert counted.content_hash() != plain.content_hash()
    # a stored record without the field reads back as before, with the same hash
    assert Peaks.from_arrays(plain.to_arrays()).content_hash() == plain.content_hash()
    numbered = NumberedLines(**_numbered_fields(), dropped=2)
    assert NumberedLines.from_arrays(numbered.to_arrays()).dropped == 2


def test_extend_carries_every_earlier_field_forward() -> None:
    peaks = Peaks(**_peak_fields(), dropped=5)
    lines = Lines.extend(peaks, line_id=np.array([0, 1, 0, 1], np.int32))
    assert lines.dropped == 5 and np.array_equal(lines.row, peaks.row)
    fields = _numbered_fields()
    ordered = OrderedLines.extend(
        lines, **{k: fields[k] for k in ("order", "line_order", "line_component")}
    )
    numbered = NumberedLines.extend(
        ordered,
        **{
            k: fields[k] for k in ("number", "line_number", "kind_observed", "confidence", "reason")
        },
    )
    by_hand = NumberedLines(**(fields | {"line_id": lines.line_id}), dropped=5)
    assert numbered.content_hash() == by_hand.content_hash()
    # a later record given to an earlier stage's class keeps only that class's fields
    assert Lines.extend(numbered, line_id=lines.line_id).content_hash() == lines.content_hash()


def test_extend_refuses_missing_fields_and_other_records() -> None:
    peaks = Peaks(**_peak_fields())
    with pytest.raises(TypeError):
        Lines.extend(peaks)
    with pytest.raises(TypeError, match="Peaks record"):
        Lines.extend(object(), line_id=np.zeros(4, np.int32))  # type: ignore[arg-type]
