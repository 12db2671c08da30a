"""Unit tests of the fits on synthetic data: hole identification, camera DLT and adjustment,
line grouping and numbering, projector adjustment and what it leaves to the reference."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rasterserver.calibration.camera_calibration import (
    assign_plates,
    calibrate_camera,
    decompose_projection,
    dlt,
)
from rasterserver.calibration.control_points import DEFAULT_HOLE_LAYOUT, load_control_points
from rasterserver.calibration.hole_identification import identify_holes
from rasterserver.calibration.projector_calibration import (
    calibrate_projector,
    group_lines,
    number_plate_lines,
)
from rasterserver.errors import InputError
from rasterserver.optics import Projector, default_station, rotation_matrix
from rasterserver.raster import default_raster


def _body_points() -> np.ndarray:
    """Control points of the seed's body (3 configurations x 2 plates x 7 holes)."""
    plates = []
    for x in (-180.0, 0.0, 180.0):
        for y, z in ((-30.0, -100.0), (30.0, 100.0)):
            holes = DEFAULT_HOLE_LAYOUT + np.array([x, y])
            plates.append(np.column_stack([holes, np.full(7, z)]))
    return np.concatenate(plates)


def test_identify_holes_orders_shuffled_points() -> None:
    rng = np.random.default_rng(1)
    image = DEFAULT_HOLE_LAYOUT @ np.array([[1.05, 0.02], [-0.03, 0.98]]) + [300.0, 280.0]
    shuffle = rng.permutation(7)
    order, rms = identify_holes(image[shuffle] + rng.normal(0, 0.05, (7, 2)),
                                DEFAULT_HOLE_LAYOUT)
    assert np.array_equal(shuffle[order], np.arange(7))
    assert rms < 0.1


def test_identify_holes_refuses_a_mirrored_or_wrong_pattern() -> None:
    mirrored = DEFAULT_HOLE_LAYOUT * [-1.0, 1.0] + 300.0
    with pytest.raises(InputError, match="do not form the control-point pattern"):
        identify_holes(mirrored, DEFAULT_HOLE_LAYOUT)
    moved = DEFAULT_HOLE_LAYOUT + 300.0
    moved[6] = [300.0, 300.0]  # marker on the centre line: not the layout
    with pytest.raises(InputError, match="do not form the control-point pattern"):
        identify_holes(moved, DEFAULT_HOLE_LAYOUT)


def test_camera_recovered_exactly_from_exact_points() -> None:
    true = default_station().camera
    xyz = _body_points()
    uv = true.project(xyz)
    k, _, _ = decompose_projection(dlt(xyz, uv))
    assert np.allclose(k, true.K, rtol=2e-3, atol=1.0)  # the DLT ignores the distortion
    fit = calibrate_camera(xyz, uv, width=true.width, height=true.height)
    assert fit.rms < 1e-6
    assert np.allclose(fit.camera.K, true.K, atol=1e-4)
    assert np.allclose(fit.camera.dist, true.dist, atol=1e-7)
    assert np.allclose(fit.camera.centre, true.centre, atol=1e-4)
    assert np.allclose(fit.camera.R, true.R, atol=1e-8)


def test_camera_refuses_coplanar_points_and_unknown_terms() -> None:
    xyz = _body_points()[:7]
    with pytest.raises(InputError, match="all on one plane"):
        dlt(xyz, default_station().camera.project(xyz))
    with pytest.raises(InputError, match="unknown distortion terms"):
        calibrate_camera(_body_points(), np.zeros((42, 2)), width=10, height=10,
                         distortion=("k9",))


def test_assign_plates_finds_the_swapped_plates() -> None:
    cam = default_station().camera
    xyz = _body_points().reshape(3, 2, 7, 3)
    observed = [[cam.project(xyz[f, 1]), cam.project(xyz[f, 0])] for f in range(3)]
    known = [[xyz[f, 0], xyz[f, 1]] for f in range(3)]
    assignment, rms, errors = assign_plates(observed, known)
    assert assignment == [(1, 0)] * 3
    assert rms < 1.0 and errors.shape == (42,)


def test_group_lines_merges_pieces_and_counts_gaps() -> None:
    cols = np.arange(100)
    rows = []
    for j in (0, 1, 2, 4, 5):  # line 3 missing
        rows.append(np.column_stack([cols, 20.0 + 10.3 * j + 0.01 * cols]))
    pts = np.concatenate(rows)
    pts = pts[~((pts[:, 1] > 40) & (pts[:, 1] < 43) & (pts[:, 0] > 40) & (pts[:, 0] < 50))]
    line, heights = group_lines(pts[:, 0].astype(int), pts[:, 1])
    expected = np.repeat([0, 1, 2, 4, 5], 100)[
        ~((np.concatenate(rows)[:, 1] > 40) & (np.concatenate(rows)[:, 1] < 43)
          & (np.concatenate(rows)[:, 0] > 40) & (np.concatenate(rows)[:, 0] < 50))
    ]
    assert np.array_equal(line, expected)
    assert np.isnan(heights[3])


def test_number_plate_lines_reads_the_code() -> None:
    raster = default_raster()
    first = 31
    cols = np.arange(60)
    col, row, area = [], [], []
    for j in range(30):
        heavy = raster.kinds[first + j] == "heavy"
        col.append(cols)
        row.append(np.full(60, 15.0 + 10.0 * j))
        # a trend in brightness over the plate, heavy lines 1.5x their light neighbours
        area.append(np.full(60, (100.0 + 3.0 * j) * (1.5 if heavy else 1.0)))
    lines = number_plate_lines(np.concatenate(col), np.concatenate(row), np.concatenate(area),
                               raster)
    assert lines.offset == first and lines.mismatches == 0
    assert np.array_equal(np.unique(lines.number), raster.numbers[first : first + 30])
    with pytest.raises(InputError, match="fewer than the code window"):
        number_plate_lines(cols, np.full(60, 5.0), np.full(60, 100.0), raster)


def test_projector_recovered_and_the_unobservable_taken_from_the_reference() -> None:
    nominal = default_station().projector
    r = rotation_matrix(-1.0, 1.5, 0.4)
    centre = np.array([15.0, -805.0, -1990.0])
    true = Projector(K=nominal.K + np.array([[20, 0, 0], [0, 20, 8], [0, 0, 0]]), dist=[-0.015],
                     R=r, t=-r @ centre, width=nominal.width, height=nominal.height)
    rng = np.random.default_rng(3)
    xyz = np.column_stack([rng.uniform(-250, 250, 4000), rng.uniform(-230, 230, 4000),
                           rng.choice([-100.0, 100.0], 4000)])
    v = true.project(xyz)[:, 1]
    fit = calibrate_projector(xyz, v, reference=nominal)
    # exact data; the misfit left is the distortion's weak dependence on the fixed t_x, c_u
    assert fit.rms < 2e-3 and fit.dlt_rms < 0.5
    assert abs(fit.projector.K[1, 1] - true.K[1, 1]) < 0.5
    assert np.allclose(fit.projector.centre[1:], true.centre[1:], atol=0.5)
    # along the lines (x) the centre is the reference's, not the truth's
    x_axis = fit.projector.R[0]
    assert abs(fit.projector.centre @ x_axis - nominal.centre @ x_axis) < 1e-6
    # ...which changes no light surface: same v for new points within 0.01 units
    test = np.column_stack([rng.uniform(-200, 200, 500), rng.uniform(-200, 200, 500),
                            rng.uniform(-150, 150, 500)])
    assert np.abs(fit.projector.project(test)[:, 1] - true.project(test)[:, 1]).max() < 0.01


def test_load_control_points_json_csv_and_errors(tmp_path: Path) -> None:
    rows = []
    for k in range(2):
        for plate, z in (("high", -100.0), ("low", 100.0)):
            for i, (x, y) in enumerate(DEFAULT_HOLE_LAYOUT):
                rows.append({"id": f"c{k}-{plate}-{i}", "configuration": k, "plate": plate,
                             "index": i, "x": x, "y": y, "z": z})
    path = tmp_path / "cp.json"
    path.write_text(json.dumps({"points": rows}))
    cpf = load_control_points(path)
    assert cpf.configurations == [0, 1] and len(cpf.plates[0]) == 2
    csv_path = tmp_path / "cp.csv"
    csv_path.write_text("id,configuration,plate,index,x,y,z\n" + "\n".join(
        ",".join(str(r[f]) for f in ("id", "configuration", "plate", "index", "x", "y", "z"))
        for r in rows))
    assert load_control_points(csv_path).plates[1][1].ids[6] == "c1-low-6"
    path.write_text(json.dumps({"points": rows[:-1]}))
    with pytest.raises(InputError, match=r"low plate of configuration 1 lacks holes \[6\]"):
        load_control_points(path)
    path.write_text(json.dumps({"points": [*rows, rows[0]]}))
    with pytest.raises(InputError, match="two points for hole 0"):
        load_control_points(path)
    with pytest.raises(InputError, match="no such control-point file"):
        load_control_points(tmp_path / "missing.json")
