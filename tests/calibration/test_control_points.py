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


# --- hole layouts (issue 13): any seven-point pattern, but one that identifies its points ---


def _with_layout(good: dict, layout: np.ndarray) -> dict:
    """The good file's points moved onto ``layout`` (each plate keeps its centre)."""
    doc = json.loads(json.dumps(good))
    for p in doc["points"]:
        centre_x = {"left": -180.0, "centre": 0.0, "right": 180.0}[p["lateral"]]
        centre_y = -30.0 if p["plate"] == "high" else 30.0
        p["x"], p["y"] = centre_x + layout[p["index"]][0], centre_y + layout[p["index"]][1]
    doc["hole_layout"] = {"plate_coordinates_mm": layout.tolist()}
    return doc


def test_an_irregular_layout_reads(tmp_path: Path, good: dict) -> None:
    from rasterserver.simulator.calibration_body import random_hole_layout

    layout = random_hole_layout(np.random.default_rng(2))
    loaded = load_control_points(_write(tmp_path, _with_layout(good, layout)))
    np.testing.assert_allclose(loaded.layout, layout)


def test_a_symmetric_layout_is_refused(tmp_path: Path, good: dict) -> None:
    angles = np.linspace(0.0, 2 * np.pi, 7, endpoint=False)
    circle = 60.0 * np.column_stack([np.cos(angles), np.sin(angles)])
    with pytest.raises(InputError, match="hole layout is symmetric"):
        load_control_points(_write(tmp_path, _with_layout(good, circle)))


def test_points_that_do_not_have_the_layout_are_refused(tmp_path: Path, good: dict) -> None:
    good["points"][10]["x"] += 25.0  # c0-low-3 surveyed off its place in the layout
    with pytest.raises(InputError, match="low plate of configuration 0 does not have the hole"):
        load_control_points(_write(tmp_path, good))


def test_a_mirrored_plate_is_refused(tmp_path: Path, good: dict) -> None:
    for p in good["points"]:
        if p["configuration"] == 1 and p["plate"] == "high":
            p["x"] = -p["x"]  # the plate's points given mirrored (x reversed)
    with pytest.raises(InputError, match="mirror image of the hole layout"):
        load_control_points(_write(tmp_path, good))


def test_a_csv_takes_its_layout_from_its_points(tmp_path: Path) -> None:
    from rasterserver.calibration.hole_identification import identify_holes
    from rasterserver.simulator.calibration_body import random_hole_layout

    layout = random_hole_layout(np.random.default_rng(5))
    path = write_control_points(tmp_path / "cp.csv", control_points(layout=layout))
    loaded = load_control_points(path)
    # the same pattern up to a rigid motion: the layout's own points identify in order
    order, _ = identify_holes(layout, loaded.layout)
    assert order.tolist() == list(range(7))
