"""Reading control-point files: every malformed file is an InputError, never a crash later."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rasterserver.calibration.control_points import load_control_points
from rasterserver.errors import InputError
from rasterserver.simulator.calibration_body import control_points, write_control_points


@pytest.fixture
def good(tmp_path: Path) -> dict:
    path = write_control_points(tmp_path / "good.json", control_points())
    return json.loads(path.read_text())


def _write(tmp_path: Path, document: object, name: str = "cp.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(document))  # NaN and Infinity as JSON writes them
    return path


def test_the_simulated_file_reads(tmp_path: Path, good: dict) -> None:
    loaded = load_control_points(_write(tmp_path, good))
    assert loaded.configurations == [0, 1, 2]


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_a_coordinate_that_is_not_finite_is_refused(
    tmp_path: Path, good: dict, value: float
) -> None:
    """Issue 11, defect 5: a NaN control point ended in 'SVD did not converge'."""
    good["points"][3]["y"] = value
    with pytest.raises(InputError, match="c0-high-3 has a coordinate that is not a finite"):
        load_control_points(_write(tmp_path, good))


def test_a_csv_nan_is_refused(tmp_path: Path) -> None:
    path = write_control_points(tmp_path / "cp.csv", control_points())
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    row = lines[1].split(",")
    row[header.index("z")] = "nan"
    path.write_text("\n".join([lines[0], ",".join(row), *lines[2:]]) + "\n")
    with pytest.raises(InputError, match="not a finite number"):
        load_control_points(path)


@pytest.mark.parametrize(
    ("layout", "message"),
    [
        ([[0.0, float("nan")]] * 7, "not finite"),
        ("x", "7 points"),
        ([[1.0, 2.0]] * 3, "7 points"),
    ],
)
def test_a_bad_hole_layout_is_refused(
    tmp_path: Path, good: dict, layout: object, message: str
) -> None:
    good["hole_layout"] = {"plate_coordinates_mm": layout}
    with pytest.raises(InputError, match=message):
        load_control_points(_write(tmp_path, good))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("[1, 2]", "not a control-point document"),
        ('{"points": {"a": 1}}', "not a control-point document"),
        ('{"points": [], "hole_layout": [1]}', "'hole_layout' must be an object"),
        ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
        ("{not json", "not JSON"),
    ],
)
def test_malformed_json_is_refused(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "cp.json"
    path.write_text(content)
    with pytest.raises(InputError, match=message):
        load_control_points(path)


def test_a_folder_or_binary_file_is_refused(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="is a folder"):
        load_control_points(tmp_path)
    binary = tmp_path / "cp.json"
    binary.write_bytes(bytes(np.random.default_rng(3).integers(128, 256, 64, np.uint8)))
    with pytest.raises(InputError, match="not UTF-8"):
        load_control_points(binary)
