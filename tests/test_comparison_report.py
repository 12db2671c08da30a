"""``report.html`` of a comparison: how each pair was registered is said when the frames
were made without a visit's VP."""

from __future__ import annotations

from pathlib import Path

import pytest

from rasterserver.comparison_report import write_report


def _pair(start_from: str) -> dict:
    distance = {
        "rms_mm": 0.07,
        "max_abs_mm": 1.0,
        "area_above_2mm_mm2": 0.0,
        "area_below_minus_2mm_mm2": 0.0,
        "displaced": 0.0,
    }
    registration = {"fitness": 0.99, "rmse_mm": 1.3, "landmark_start_from": start_from}
    files = ["distance_a-b.ply", "distance_a-b.png"]
    return {"a": "a", "b": "b", "distance": distance, "registration": registration, "files": files}


@pytest.mark.parametrize(
    ("start_from", "said"),
    [
        ("VP, DL and DR of both visits", False),
        ("VP of visit a not found: both visits' frames from DM, DL → DR and ...", True),
        ("VP of neither visit found: both visits' frames from DM, DL → DR and ...", True),
    ],
)
def test_frames_without_vp_are_said(tmp_path: Path, start_from: str, said: bool) -> None:
    write_report(tmp_path, [], [_pair(start_from)], [], {})
    text = (tmp_path / "report.html").read_text(encoding="utf-8")
    assert ("frames from DM, DL → DR" in text) is said
    assert "distance rms 0.07 mm" in text
