"""``rasterserver reconstruct``: one frame to a PLY point cloud and an overlay, no archive."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import geometry_truth as gt
import numpy as np
import open3d as o3d
import pytest

from rasterserver.cli import main
from rasterserver.optics import default_station


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("reconstruct")
    station = gt.station()
    paths = {
        "frame": folder / "frame.png",
        "calibration": station.save(folder / "calibration.json"),
        "raster": station.raster_definition.save(folder / "raster.json"),
        "black": folder / "black.png",
        "small": folder / "small.png",
        "other": default_station(width=640, height=480).save(folder / "other.json"),
        "broken": folder / "broken.json",
    }
    cv2.imwrite(str(paths["frame"]), gt.rendering("back").image)
    cv2.imwrite(str(paths["black"]), np.zeros((604, 576), np.uint8))
    cv2.imwrite(str(paths["small"]), gt.rendering("back").image[::2, ::2])
    paths["broken"].write_text("{ not json")
    return paths


def _read_ply(path: Path) -> o3d.t.geometry.PointCloud:
    cloud = o3d.t.io.read_point_cloud(str(path))
    assert cloud.point.positions.shape[0] > 0
    return cloud


def test_points_with_their_attributes(files, tmp_path: Path, capsys) -> None:
    out = tmp_path / "back.ply"
    code = main(["reconstruct", str(files["frame"]), "--calibration", str(files["calibration"]),
                 "-o", str(out)])
    assert code == 0
    assert "points written to" in capsys.readouterr().out
    cloud = _read_ply(out)
    xyz = cloud.point.positions.numpy()
    assert xyz.dtype == np.float64 and 15_000 < len(xyz) < 30_000
    for name, dtype in (("number", np.int32), ("col", np.int32), ("area", np.float32),
                        ("row", np.float64)):
        values = cloud.point[name].numpy().ravel()
        assert values.dtype == dtype and values.shape == (len(xyz),)
    numbers = cloud.point["number"].numpy().ravel()
    assert set(numbers) <= set(gt.station().raster_definition.numbers.tolist())
    cols = cloud.point["col"].numpy().ravel()
    assert cols.min() >= 0 and cols.max() < 576
    assert np.all(cloud.point["area"].numpy() > 0)
    # mm in the calibration's world frame, on the simulated back
    assert gt.rms(gt.distance_to_scene(gt.scene("back"), xyz)) <= 0.5


def test_overlay_and_smoothed_points(files, tmp_path: Path) -> None:
    out, overlay = tmp_path / "s.ply", tmp_path / "overlay.png"
    code = main(["reconstruct", str(files["frame"]), "--calibration", str(files["calibration"]),
                 "--raster", str(files["raster"]), "-o", str(out), "--smoothed",
                 "--overlay", str(overlay), "--stage", "surface=surface.linear-grid"])
    assert code == 0
    image = cv2.imread(str(overlay), cv2.IMREAD_COLOR)
    # the frame twice enlarged, and under it (when something is unnumbered) the reasons
    assert image.shape[1] == 1152 and image.shape[0] >= 1208
    hsv = cv2.cvtColor(image[:1208], cv2.COLOR_BGR2HSV)
    assert np.count_nonzero(hsv[..., 1] > 150) > 20_000  # coloured lines and numbers
    smoothed = _read_ply(out).point.positions.numpy()
    full = tmp_path / "full.ply"
    main(["reconstruct", str(files["frame"]), "--calibration", str(files["calibration"]),
          "-o", str(full)])
    assert len(smoothed) == pytest.approx(len(_read_ply(full).point.positions) / 3, rel=0.05)
    assert gt.rms(gt.distance_to_scene(gt.scene("back"), smoothed)) <= 0.2


@pytest.mark.parametrize(
    ("args", "code", "message"),
    [
        (["{black}", "--calibration", "{calibration}"], 2, "no points to write"),
        (["{small}", "--calibration", "{calibration}"], 2, "wrong calibration"),
        (["{frame}", "--calibration", "{other}"], 2, "wrong calibration"),
        (["{frame}", "--calibration", "{raster}"], 2, "this is a raster definition"),
        (["{frame}", "--calibration", "{broken}"], 2, "not a JSON calibration"),
        (["{frame}", "--calibration", "{missing}"], 2, "no such calibration file"),
        (["{frame}", "--calibration", "{calibration}", "--raster", "{calibration}"], 2,
         "this is a calibration"),
        (["{frame}", "--calibration", "{calibration}", "--stage", "points=points.nope"], 3,
         "no stage plugin named 'points.nope'"),
        (["{frame}", "--calibration", "{calibration}", "--stage", "points"], 2, "KIND=PLUGIN"),
        (["{frame}", "--calibration", "{calibration}", "--stage", "mesh=points.ray-plane"], 2,
         "implements stage 'points'"),
        (["{broken}", "--calibration", "{calibration}"], 2, "broken.json"),
    ],
    ids=["all-black", "frame-size", "other-camera", "raster-as-calibration", "not-json",
         "missing-calibration", "calibration-as-raster", "unknown-plugin", "bad-stage-option",
         "plugin-of-other-stage", "not-an-image"],
)
def test_bad_input_is_a_clear_message(files, tmp_path, capsys, args, code, message) -> None:
    names = {k: str(v) for k, v in files.items()} | {"missing": str(tmp_path / "none.json")}
    out = tmp_path / "out.ply"
    argv = ["reconstruct", *(a.format(**names) for a in args), "-o", str(out)]
    assert main(argv) == code
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and "Traceback" not in err
    assert not out.exists()


def test_black_frame_overlay_is_still_written(files, tmp_path: Path, capsys) -> None:
    overlay = tmp_path / "o.png"
    argv = ["reconstruct", str(files["black"]), "--calibration", str(files["calibration"]),
            "-o", str(tmp_path / "o.ply"), "--overlay", str(overlay)]
    assert main(argv) == 2
    assert "no peaks" in capsys.readouterr().err
    assert overlay.is_file()
    # the reason is printed under the (black) frame: a white panel with black text
    image = cv2.imread(str(overlay), cv2.IMREAD_GRAYSCALE)
    panel = image[1208:]
    assert panel.shape[0] > 20 and np.mean(panel) > 200 and np.count_nonzero(panel < 100) > 50


def test_output_must_be_ply(files, tmp_path: Path, capsys) -> None:
    argv = ["reconstruct", str(files["frame"]), "--calibration", str(files["calibration"]),
            "-o", str(tmp_path / "x.xyz")]
    assert main(argv) == 2
    assert ".ply" in capsys.readouterr().err


def test_raster_from_the_calibration_document(files, tmp_path: Path) -> None:
    # a calibration holding its raster inline, as a station's own document would
    document = json.loads(files["calibration"].read_text())
    document["raster"] = json.loads(files["raster"].read_text())
    inline = tmp_path / "inline.json"
    inline.write_text(json.dumps(document))
    out = tmp_path / "i.ply"
    assert main(["reconstruct", str(files["frame"]), "--calibration", str(inline),
                 "-o", str(out)]) == 0
    document["raster"] = "no-such-raster"
    inline.write_text(json.dumps(document))
    assert main(["reconstruct", str(files["frame"]), "--calibration", str(inline),
                 "-o", str(out)]) == 2
