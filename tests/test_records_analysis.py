"""The BackShape record: validation, storage round trip, summary, and combining frames."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rasterserver.errors import InputError
from rasterserver.records_analysis import LANDMARKS, SAGITTAL_POINTS, BackShape, combine


def _shape(
    *,
    shift: float = 0.0,
    length: float = 440.0,
    missing: tuple[str, ...] = (),
    extra: dict[str, float] | None = None,
) -> BackShape:
    """A small, complete analysis whose landmarks move by ``shift`` mm along x."""
    # VP, DL, DR, DM, SP
    landmarks = np.array(
        [
            [0.0, -230.0, 10.0],
            [-50.0, 210.0, 5.0],
            [50.0, 210.0, 5.0],
            [0.0, 210.0, 2.0],
            [0.0, 270.0, -5.0],
        ]
    )
    landmarks[:, 0] += shift
    confidence = np.full(len(LANDMARKS), 0.8)
    reasons = {}
    for name in missing:
        k = LANDMARKS.index(name)
        landmarks[k] = np.nan
        confidence[k] = 0.0
        reasons[name] = "covered by an arm"
    params = {
        "trunk_length": {"value": length, "unit": "mm", "spread": None},
        "surface_rotation_max_deg": {"value": shift / 2.0, "unit": "deg", "spread": None},
    }
    for name, value in (extra or {}).items():
        params[name] = {"value": value, "unit": "mm", "spread": None}
    line = np.column_stack([np.full(5, shift), np.linspace(-230.0, 210.0, 5), np.zeros(5)])
    axes = np.eye(3)
    return BackShape(
        x0=-30.0,
        y0=-300.0,
        spacing=3.0,
        mean_curvature=np.full((4, 5), shift, dtype=np.float32),
        gaussian_curvature=np.zeros((4, 5), dtype=np.float32),
        landmarks=landmarks,
        landmark_confidence=confidence,
        frame_origin=landmarks[3].copy(),
        frame_axes=axes,
        symmetry_line=line,
        surface_rotation=np.zeros(5),
        midline=line + np.array([0.0, 0.0, 50.0]),
        parameters=json.dumps(params),
        reasons=json.dumps(reasons),
        max_curvature=np.zeros((4, 5), dtype=np.float32),
        min_curvature=np.zeros((4, 5), dtype=np.float32),
        principal_direction=np.zeros((4, 5), dtype=np.float32),
        sagittal_points=np.tile([[0.0, 0.0, 1.0]], (len(SAGITTAL_POINTS), 1)),
        level_axes=np.eye(3),
    )


def test_round_trip_and_summary() -> None:
    shape = _shape(missing=("SP",))
    again = BackShape.from_arrays(shape.to_arrays())
    assert again == shape
    summary = again.summary()
    assert summary["landmarks"]["SP"] is None and summary["landmarks"]["VP"] == [0.0, -230.0, 10.0]
    assert summary["sagittal_points"]["KA"] == [0.0, 0.0, 1.0]
    assert summary["parameters"]["trunk_length"] == {"value": 440.0, "unit": "mm", "spread": None}
    assert summary["reasons"] == {"SP": "covered by an arm"}
    assert again.sagittal_point("ICT") is not None
    with pytest.raises(InputError, match="no sagittal point"):
        again.sagittal_point("XYZ")


def test_validation_of_the_new_fields() -> None:
    shape = _shape()
    arrays = shape.to_arrays()
    arrays["max_curvature"] = np.zeros((3, 3), dtype=np.float32)
    with pytest.raises(InputError, match="max_curvature"):
        BackShape.from_arrays(arrays)
    arrays = shape.to_arrays()
    arrays["sagittal_points"] = np.zeros((4, 3))
    with pytest.raises(InputError, match="sagittal_points"):
        BackShape.from_arrays(arrays)
    # the optional maps may be absent (records of the first contract)
    empty = BackShape.empty("nothing")
    assert empty.max_curvature is None and empty.summary()["sagittal_points"]["KA"] is None


def test_combine_gives_mean_and_spread() -> None:
    shapes = [_shape(shift=s, length=440.0 + s) for s in (0.0, 2.0, 4.0)]
    out = combine(shapes)
    params = out.parameter_table()
    assert params["trunk_length"]["value"] == pytest.approx(442.0)
    assert params["trunk_length"]["spread"] == pytest.approx(2.0)  # sample std of 440, 442, 444
    assert params["surface_rotation_max_deg"]["unit"] == "deg"
    np.testing.assert_allclose(out.landmark("VP"), [2.0, -230.0, 10.0])
    np.testing.assert_allclose(out.frame_axes, np.eye(3), atol=1e-12)
    # maps and lines come from the frame closest to the means: the middle one
    assert float(out.mean_curvature[0, 0]) == 2.0
    np.testing.assert_allclose(out.symmetry_line[:, 0], 2.0)
    assert out.reason == "" and out.reason_table() == {}


def test_combine_reports_what_some_frames_missed() -> None:
    shapes = [
        _shape(shift=0.0),
        _shape(shift=2.0, missing=("DL",)),
        _shape(shift=4.0, extra={"asymmetry_rms_mm": 3.0}),
        BackShape.empty("no back recognised"),
    ]
    out = combine(shapes)
    reasons = out.reason_table()
    np.testing.assert_allclose(out.landmark("DL"), [-48.0, 210.0, 5.0])
    assert reasons["DL"] == "found in 2 of 3 frames"
    assert reasons["asymmetry_rms_mm"] == "computed on 1 of 3 frames"
    assert reasons["frames"] == "1 of 4 frames not analysed"
    assert out.parameter_table()["asymmetry_rms_mm"]["spread"] is None
    assert out.landmark_confidence[LANDMARKS.index("DL")] == pytest.approx(0.8 * 2 / 3)


def test_combine_single_and_failed_frames() -> None:
    one = _shape()
    assert combine([one]) is one
    failed = combine([BackShape.empty("no surface"), BackShape.empty("no back recognised")])
    assert "no frame could be analysed" in failed.reason
    assert "no surface" in failed.reason and "no back recognised" in failed.reason
    missing_everywhere = combine([_shape(missing=("SP",)), _shape(missing=("SP",))])
    assert missing_everywhere.landmark("SP") is None
    assert missing_everywhere.reason_table()["SP"] == "covered by an arm"
    with pytest.raises(InputError):
        combine([])
