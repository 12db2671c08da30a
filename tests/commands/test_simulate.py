"""``rasterserver simulate``: files written, sane images and ground truth, bad options."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from rasterserver.cli import main
from rasterserver.simulator.ground_truth import load_ground_truth

# Half-size images and one sample per pixel keep the tests quick; the field of view is kept.
FAST = ["--supersample", "1", "--width", "288", "--height", "302"]


def test_back_writes_frame_truth_and_calibration(tmp_path: Path) -> None:
    out = tmp_path / "back"
    code = main(
        ["simulate", "back", "--preset", "moderate", "--rotation", "12", "--out", str(out), *FAST]
    )
    assert code == 0
    names = {p.name for p in out.iterdir()}
    assert names == {"frame.png", "frame_truth.npz", "back.json", "calibration.json", "raster.json"}
    image = cv2.imread(str(out / "frame.png"), cv2.IMREAD_UNCHANGED)
    assert image.shape == (302, 288) and image.dtype == np.uint8
    assert image.max() > 10 and image.mean() > 2
    truth = load_ground_truth(out / "frame_truth.npz")
    assert truth["points"].shape == (302, 288, 3)
    assert {"vertebra_prominens", "dimple_left", "dimple_right", "spinal_midline"} <= set(
        truth["landmarks"]
    )
    assert truth["object_names"] == ["trunk", "left-arm", "right-arm"]
    params = json.loads((out / "back.json").read_text())
    assert params["curves"][0]["rotation"] == 12.0
    assert truth["scene_metadata"]["parameters"] == params
    assert json.loads((out / "calibration.json").read_text())["format"].startswith("rasterserver")
    json.loads((out / "raster.json").read_text())


def test_back_npy_16_bit_without_noise_is_deterministic(tmp_path: Path) -> None:
    args = ["simulate", "back", "--preset", "normal", "--format", "npy", "--bit-depth", "16"]
    for name in ("a", "b"):
        assert main([*args, "--no-noise", "--out", str(tmp_path / name), *FAST]) == 0
    a = np.load(tmp_path / "a" / "frame.npy")
    assert a.dtype == np.uint16 and a.shape == (302, 288) and a.max() > 255
    np.testing.assert_array_equal(a, np.load(tmp_path / "b" / "frame.npy"))
    assert not (tmp_path / "a" / "frame.png").exists()


def test_random_back_and_visits(tmp_path: Path) -> None:
    out = tmp_path / "visits"
    assert (
        main(
            [
                "simulate",
                "back",
                "--random-back",
                "5",
                "--visits",
                "2",
                "--out",
                str(out),
                "--lateral-deviation",
                "10",
                *FAST,
            ]
        )
        == 0
    )
    first = json.loads((out / "visit-01" / "back.json").read_text())
    second = json.loads((out / "visit-02" / "back.json").read_text())
    assert first["curves"][0]["lateral_deviation"] == 10.0
    assert second["curves"][0]["lateral_deviation"] == pytest.approx(11.5)


def test_calibration_body_writes_six_frames(tmp_path: Path) -> None:
    out = tmp_path / "cal"
    assert main(["simulate", "calibration-body", "--out", str(out), *FAST]) == 0
    for k in range(3):
        on = cv2.imread(str(out / f"config{k}-projector-on.png"), cv2.IMREAD_UNCHANGED)
        off = cv2.imread(str(out / f"config{k}-projector-off.png"), cv2.IMREAD_UNCHANGED)
        assert on.shape == off.shape == (302, 288)
        assert (out / f"config{k}-projector-off_truth.npz").exists()
        truth = load_ground_truth(out / f"config{k}-projector-off_truth.npz")
        assert truth["landmarks"]["control_points"].shape == (14, 3)
        # Projector off: no raster line is lit anywhere.
        assert (truth["line_number"] == -1).all() and len(truth["line_rows"]) == 0
        # ... and the velvet holes image dark on the bright plates.
        uv = truth["station"].camera.project(truth["landmarks"]["control_points"])
        uv = np.rint(uv).astype(int)
        holes = off[uv[:, 1], uv[:, 0]].astype(float)
        plates = off[uv[:, 1] + 8, uv[:, 0]].astype(float)
        assert (plates > holes + 20).all()
        assert (
            load_ground_truth(out / f"config{k}-projector-on_truth.npz")["line_number"] >= 0
        ).any()
    doc = json.loads((out / "control_points.json").read_text())
    assert len(doc["points"]) == 42
    assert (out / "calibration.json").exists() and (out / "raster.json").exists()


def test_ingest_progressing_visits(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    archive = tmp_path / "archive"
    args = ["--archive", str(archive), "simulate", "back", "--preset", "moderate"]
    code = main(
        [
            *args,
            "--visits",
            "2",
            "--ingest",
            "--patient",
            "SIM-1",
            "--out",
            str(tmp_path / "out"),
            *FAST,
        ]
    )
    assert code == 0
    uids = [
        line.split()[-1]
        for line in capsys.readouterr().out.splitlines()
        if line.startswith("ingested")
    ]
    assert len(uids) == 2
    from rasterserver.archive import Archive
    from rasterserver.config import Settings

    with Archive(Settings.from_env(archive=archive)) as arch:
        acquisitions = arch.acquisitions(patient="SIM-1")
        assert len(acquisitions) == 2
        frame = arch.read_frame(uids[0])
        assert frame.shape == (302, 288)
        assert len(arch.calibrations("simulator")) == 1
    # A second run reuses the station's calibration.
    assert (
        main([*args, "--ingest", "--patient", "SIM-1", "--out", str(tmp_path / "o2"), *FAST]) == 0
    )
    with Archive(Settings.from_env(archive=archive)) as arch:
        assert len(arch.calibrations("simulator")) == 1
        assert len(arch.acquisitions(patient="SIM-1")) == 3


@pytest.mark.parametrize(
    "args",
    [
        ["back", "--preset", "mild"],
        ["back", "--rotation", "75"],
        ["back", "--lateral-deviation", "500"],
        ["back", "--trunk-length", "-10"],
        ["back", "--bit-depth", "12"],
        ["back", "--supersample", "0"],
        ["back", "--width", "10"],
        ["back", "--visits", "0"],
        ["back", "--ingest"],
        ["calibration-body", "--hole-radius", "0"],
    ],
)
def test_bad_options_exit_2(args: list[str], tmp_path: Path) -> None:
    assert main(["simulate", *args, "--out", str(tmp_path / "x")]) == 2


def test_help_texts(capsys: pytest.CaptureFixture[str]) -> None:
    for args in (
        ["simulate", "--help"],
        ["simulate", "back", "--help"],
        ["simulate", "calibration-body", "--help"],
    ):
        assert main(args) == 0
    text = capsys.readouterr().out
    assert "control_points.json" in text and "--lateral-deviation" in text
