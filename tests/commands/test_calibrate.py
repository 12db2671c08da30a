"""``rasterserver calibrate`` and ``export-calibration`` end to end, on SQLite and PostgreSQL:
the verdict, the stored version with its frames, and reprocessing an old acquisition with it."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import geometry_truth as gt
import numpy as np
import pytest

from rasterserver.archive import Archive
from rasterserver.cli import main
from rasterserver.config import Settings
from rasterserver.documents import calibration_from_document, load_calibration_document
from rasterserver.pipeline import Pipeline

sys.path.insert(0, str(Path(__file__).parents[1] / "calibration"))
from calibration_frames import rendered_dir


@pytest.fixture
def setup(settings: Settings):
    archive, uids = gt.archive_with_frames(settings, {"back": gt.rendering("back").image})
    archive.close()
    base = ["--archive", str(settings.archive), "--database-url", settings.database_url]

    def run(*args: str) -> int:
        return main([*base, *args])

    return run, uids


def test_dry_run_reports_and_stores_nothing(tmp_path: Path, capsys) -> None:
    frames = rendered_dir()
    report = tmp_path / "report.png"
    code = main(
        [
            "calibrate",
            str(frames),
            "--station",
            "sim",
            "--dry-run",
            "--report",
            str(report),
            "--output",
            str(tmp_path / "cal.json"),
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "c0-high-6" in out and "verdict: PASS" in out and "dry run: nothing stored" in out
    assert report.stat().st_size > 10_000 and report.with_suffix(".txt").exists()
    station = load_calibration_document(Path(tmp_path / "cal.json"))
    assert station.camera.width == 576


def test_worse_than_the_bounds_exits_7(tmp_path: Path, capsys) -> None:
    code = main(["calibrate", str(rendered_dir()), "--dry-run", "--max-rms-px", "0.001"])
    captured = capsys.readouterr()
    assert code == 7  # 6 is 'catalogue schema not current'
    assert "verdict: FAIL: control points" in captured.out
    assert "calibration rejected, nothing stored" in captured.err


def test_bad_inputs_say_what_is_wrong(tmp_path: Path, capsys) -> None:
    assert main(["calibrate", str(tmp_path / "nowhere"), "--dry-run"]) == 2
    assert "no such folder" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path), "--dry-run"]) == 2
    assert "no config<k>-projector-on/off frames" in capsys.readouterr().err
    assert main(["calibrate", str(rendered_dir())]) == 2
    assert "--station is needed" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("option", "name", "message"),
    [
        ("-o", "", "is a folder"),
        ("-o", "missing/cal.json", "does not exist"),
        ("-o", "file.txt/cal.json", "Not a directory"),
        ("--report", "residuals.txt", "name an image"),
        ("--report", "residuals.xyz", "name an image"),
        ("--report", "missing/residuals.png", "does not exist"),
    ],
)
def test_outputs_that_cannot_be_written_are_refused_before_the_work(
    tmp_path: Path, capsys, option: str, name: str, message: str
) -> None:
    """Issue 11, defect 5: `calibrate -o` into a missing folder was a traceback after the
    work. The frames folder does not exist either: the outputs are checked first."""
    (tmp_path / "file.txt").write_text("x")
    target = str(tmp_path / name) if name else str(tmp_path)
    assert main(["calibrate", str(tmp_path / "nowhere"), "--dry-run", option, target]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt"]


def test_calibrate_stores_a_version_and_old_acquisitions_reprocess_with_it(
    setup, settings: Settings, tmp_path: Path, capsys
) -> None:
    cli, uids = setup
    back = uids["back"]
    assert cli("process", back, "--until", "points") == 0
    capsys.readouterr()

    assert cli("calibrate", str(rendered_dir()), "--station", gt.STATION_NAME) == 0
    out = capsys.readouterr().out
    assert f"station {gt.STATION_NAME}: calibration version 2 stored" in out

    with Archive(settings) as archive:
        rows = archive.calibrations(gt.STATION_NAME)
        assert [r.version for r in rows] == [1, 2]
        new = rows[1]
        assert new.residuals["camera"]["rms_px"] <= 0.1
        assert new.source_acquisition_id is not None
        source = next(
            a for a in archive.acquisitions(limit=100) if a.id == new.source_acquisition_id
        )
        acq = archive.acquisition(source.uid)
        assert acq.kind == "calibration"
        roles = sorted(f.role for f in acq.frames)
        assert roles == ["projector-off"] * 3 + ["projector-on"] * 3
        assert new.raster_id == rows[0].raster_id  # the same diapositive, stored once

    # the old acquisition keeps its v1 results and gains v2 results beside them
    assert cli("process", back, "--until", "points", "--calibration", f"{gt.STATION_NAME}:2") == 0
    capsys.readouterr()
    with Archive(settings) as archive:
        results = Pipeline(archive).results(back)
        points = [r for r in results if r.stage == "points"]
        assert len(points) == 2
        assert {r.calibration_id for r in points} == {rows[0].id, rows[1].id}
        # image stages do not depend on the calibration: computed once, reused
        assert len([r for r in results if r.stage == "peaks"]) == 1

    exported = tmp_path / "v2.json"
    assert cli("export-calibration", f"{gt.STATION_NAME}:2", "-o", str(exported)) == 0
    station = load_calibration_document(Path(exported))
    assert np.allclose(station.camera.K, calibration_from_document(rows[1].parameters).camera.K)
    assert json.loads(exported.read_text())["name"] == gt.STATION_NAME


def test_a_missing_frame_is_refused_with_its_name(tmp_path: Path, capsys) -> None:
    import shutil

    frames = tmp_path / "frames"
    shutil.copytree(rendered_dir(), frames)
    (frames / "config1-projector-on.png").unlink()
    assert main(["calibrate", str(frames), "--dry-run"]) == 2
    assert "frame config1-projector-on is missing" in capsys.readouterr().err


def test_distortion_terms_are_chosen_and_checked(capsys) -> None:
    frames = str(rendered_dir())
    # without the camera's k1 = -0.05 the control points misfit (0.05 against 0.02 px rms)
    tight = ["--max-rms-px", "0.04"]
    assert main(["calibrate", frames, "--dry-run", *tight]) == 0
    assert main(["calibrate", frames, "--dry-run", *tight, "--camera-distortion", "none"]) == 7
    assert "verdict: FAIL: control points" in capsys.readouterr().out
    assert main(["calibrate", frames, "--dry-run", "--camera-distortion", "k1,k7"]) == 2
    assert "unknown distortion terms ['k7']" in capsys.readouterr().err
    assert main(["calibrate", frames, "--dry-run", "--camera-distortion", "k1,p1,p2"]) == 0


def test_the_body_as_a_clinic_sees_it_calibrates(tmp_path: Path) -> None:
    """Issue 13: a base as bright as the plates, columns, uneven light and an irregular hole
    layout, simulated and calibrated by the installed commands."""
    from installed_cli import TRACEBACK, run_installed

    out = tmp_path / "clinic"
    made = run_installed("simulate", "calibration-body", "--clinic-body", "--layout-seed", "3",
                         "--supersample", "2", "--out", str(out))
    assert made.returncode == 0, made.stderr
    layout = json.loads((out / "control_points.json").read_text())["hole_layout"]
    assert layout["plate_coordinates_mm"][6] != [20.0, 60.0]  # not the default pattern
    done = run_installed("calibrate", str(out), "--dry-run", "--max-rms-px", "0.05")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "verdict: PASS" in done.stdout and TRACEBACK not in done.stderr
